"""Property-based tests with hypothesis (issue #8, item 4).

The expensive pieces (simulated trajectories, reference fits) are built once per
module and cached; hypothesis chooses subsets, scalings, permutations, parameters
and corruptions of them. Each property runs 200 examples.

Measured (noise-free and noisy cart-pendulum, 300 rows): a change of units of the
cart coordinate (10^-3..10^3), of time and of energy changes the coefficients by
the expected factors to ~1e-10 relative (the tolerance of the row/column balancing);
a permutation of the rows changes them by ~1e-13 relative (the Gram matrix is summed
in another order). The tests allow 1e-8 and 1e-10.
"""

import functools
import os
import warnings

import numpy as np
import pandas as pd
import pytest
import sympy as sp
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy._expr import symbols_for
from lagsindy.solvers import StagedFISTA
from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum

# 200 examples per property with LAGSINDY_FULL_PROPERTIES=1 (the thorough run, about
# 2 minutes of CPU more); 50 in the default suite, which must stay under 5 minutes.
MAX_EXAMPLES = 200 if os.environ.get("LAGSINDY_FULL_PROPERTIES") else 50
# The default suite draws the same examples on every run and machine (a CI failure
# must reproduce); the thorough run explores new ones each time.
SETTINGS = settings(
    max_examples=MAX_EXAMPLES,
    derandomize=not os.environ.get("LAGSINDY_FULL_PROPERTIES"),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)

PEND_TERMS = ["theta_dot**2", "cos(theta)", "theta**2", "theta_dot**2*cos(theta)"]
CART_TERMS = [
    "x_dot**2",
    "theta_dot**2",
    "x_dot*theta_dot*cos(theta)",
    "cos(theta)",
    "x**2",
    "x*cos(theta)",
    "theta_dot**2*cos(theta)",
]
CART_TRUTH = {
    "x_dot**2": 0.75,
    "theta_dot**2": 0.25,
    "theta_dot*x_dot*cos(theta)": 0.5,
    "cos(theta)": 4.905,
}
SYSTEMS = {
    "pendulum": (single_pendulum, ["theta"], PEND_TERMS, "paper"),
    "cart": (cart_pendulum, ["x", "theta"], CART_TERMS, "sincos"),
}


# ----------------------------------------------------------------- cached pieces
@functools.cache
def dataset(system, active, noise=0.0):
    make, _, _, excitation = SYSTEMS[system]
    return make_dataset(
        make(),
        n_trajectories=3,
        duration=1.0,
        excitation=excitation if active else None,
        noise=noise,
        protocol="paper",
        random_state=3 if active else 4,
    )


@functools.cache
def library(system):
    _, coords, terms, _ = SYSTEMS[system]
    return CandidateLibrary.from_terms(coords, terms).build()


def fit(lib, X, tau=None, **params):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # warnings are allowed; errors are not
        return LagrangianSINDy(lib, **params).fit(X, tau)


@functools.cache
def reference(system, case, noise=0.0, lam=1e-3, threshold=0.05):
    data = dataset(system, case == "forces", noise)
    params = dict(lam=lam, solver=StagedFISTA(threshold=threshold))
    if case == "fixed":
        params["fixed_term"] = "theta_dot**2"
    return fit(
        library(system), data.X, data.tau if case == "forces" else None, **params
    )


@functools.cache
def unit_exponents(system):
    """Per term: (power of the cart coordinate's unit, power of the time unit)."""
    (x, _), (xd, thd), _ = symbols_for(["x", "theta"])
    return np.array(
        [
            [sp.degree(t, x) + sp.degree(t, xd), sp.degree(t, xd) + sp.degree(t, thd)]
            for t in library(system).terms_
        ],
        dtype=float,
    )


def log_scale(lo, hi):
    return st.floats(lo, hi).map(lambda e: 10.0**e)


# ----------------------------------------------------------------- valid input
@SETTINGS
@given(data=st.data())
def test_valid_input_never_crashes_and_gives_finite_coefficients(data):
    system = data.draw(st.sampled_from(list(SYSTEMS)), label="system")
    active = data.draw(st.booleans(), label="active")
    ds = dataset(system, active, 0.0 if data.draw(st.booleans()) else 0.05)
    lib = library(system)
    n_dof = len(lib.coordinates_)
    n = len(ds.X)
    length = data.draw(st.integers(len(lib) // n_dof + 2, n), label="rows")
    start = data.draw(st.integers(0, n - length), label="start")
    rows = slice(start, start + length)
    X = ds.X[rows] * np.repeat(
        [data.draw(log_scale(-2, 2), label=f"scale {g}") for g in ("q", "qd", "qdd")],
        n_dof,
    )
    tau = (
        None
        if not active
        else ds.tau[rows] * data.draw(log_scale(-3, 3), label="tau scale")
    )
    params = dict(
        lam=data.draw(st.floats(0.0, 2.0), label="lam"),
        alpha=data.draw(st.none() | log_scale(-3, 3), label="alpha"),
        solver=StagedFISTA(
            threshold=data.draw(st.floats(0.0, 0.5), label="threshold"),
            max_stages=data.draw(st.integers(1, 4), label="max_stages"),
            debias=data.draw(st.booleans(), label="debias"),
            max_iter=500,
        ),
        normalize=data.draw(st.booleans(), label="normalize"),
    )
    if not active:
        params["fixed_term"] = data.draw(
            st.sampled_from(["theta_dot**2", "cos(theta)"])
        )
    if data.draw(st.booleans(), label="DataFrame"):
        X = pd.DataFrame(X, columns=ds.feature_names)
    if tau is not None and n_dof == 1 and data.draw(st.booleans(), label="1-D tau"):
        tau = tau[:, 0]
    est = fit(lib, X, tau, **params)
    assert est.coef_.shape == (len(lib),)
    assert np.all(np.isfinite(est.coef_))
    assert np.all(np.isfinite(est.predict(X)))
    assert np.isfinite(est.residual_)
    # ... and on a real model, not the all-zero one that would pass the checks above
    if not active:
        assert est.coef_[lib.index(params["fixed_term"])] == 1.0  # sets the scale
    else:
        # All-zero coefficients only from a fit that says it explains nothing (and
        # warns): a strong lam without the refit, or a refit whose thresholding
        # removes the terms that carry tau (5 rows of the cart, threshold 0.125).
        # Measured over 200 examples: 0 all-zero models, 0 with residual_ == 1.
        # Or friction carries tau: 6 rows of the pendulum with lam=1 leave the
        # Lagrangian zero and the automatic friction (viscous, Coulomb) at a
        # relative residual of 0.061; that fit warns that the Lagrangian is zero.
        carried = np.any(est.coef_) or np.any(est.dissipation_coef_)
        assert carried or est.residual_ == 1.0


# ----------------------------------------------------------------- invalid input
def _not_a_number(text):
    try:
        np.asarray(text, dtype=float)
    except (TypeError, ValueError):
        return True
    return False


def _corrupt(kind, X, tau, draw):
    """(X, tau, params) with one thing wrong, and a word the message must hold."""
    n, p = X.shape
    row = draw(st.integers(0, n - 1), label="row")
    if kind == "non-finite X":
        X = X.copy()
        X[row, draw(st.integers(0, p - 1))] = draw(
            st.sampled_from([np.nan, np.inf, -np.inf])
        )
        return X, tau, {}, f"row {row}"
    if kind == "non-finite tau":
        tau = tau.copy()
        tau[row, draw(st.integers(0, tau.shape[1] - 1))] = draw(
            st.sampled_from([np.nan, np.inf, -np.inf])
        )
        return X, tau, {}, f"row {row}"
    if kind == "text in X":
        X = X.astype(object)
        X[row, draw(st.integers(0, p - 1))] = draw(
            st.text(max_size=8).filter(_not_a_number)
        )
        return X, tau, {}, f"row {row}"
    if kind == "columns":
        extra = draw(
            st.integers(1 - p, 7).filter(lambda k: k != 0), label="extra columns"
        )
        X = (
            X[:, : p + extra]
            if extra < 0
            else np.hstack([X, np.tile(X[:, :1], (1, extra))])
        )
        return X, tau, {}, "n_features ="
    if kind == "tau rows":
        cut = draw(st.integers(1, n - 1), label="missing tau rows")
        return X, tau[cut:], {}, "different numbers of rows"
    if kind == "tau columns":
        k = draw(
            st.integers(1, 4).filter(lambda k: k != tau.shape[1]), label="tau columns"
        )
        return X, np.tile(tau[:, :1], (1, k)), {}, "tau must have shape"
    if kind == "dimensions":
        shape = draw(st.sampled_from(["1-D", "3-D", "scalar"]))
        X = {"1-D": X.ravel(), "3-D": X[:, :, None], "scalar": X[0, 0]}[shape]
        return X, tau, {}, "array"
    if kind == "too few rows":
        k = draw(st.integers(2, 3))
        return X[:k], tau[:k], {}, "too few samples"
    if kind == "no motion":
        d = p // 3
        X = X.copy()
        X[:, d:] = 0.0
        return X, tau, {}, "velocities"
    if kind == "parameter":
        name, value = draw(
            st.one_of(
                st.tuples(
                    st.just("lam"), st.floats(max_value=-1e-12) | st.just(np.nan)
                ),
                st.tuples(st.just("alpha"), st.floats(max_value=0.0)),
                st.tuples(
                    st.just("threshold"),
                    st.floats(min_value=1.0) | st.floats(max_value=-1e-9),
                ),
                st.tuples(st.just("max_iter"), st.integers(max_value=0)),
                st.tuples(
                    st.just("case"),
                    st.text(max_size=6).filter(
                        lambda s: s not in ("auto", "forces", "fixed", "acceleration")
                    ),
                ),
            ),
            label="parameter",
        )
        return X, tau, {name: value}, name
    if kind == "unknown term":
        name = draw(
            st.from_regex(r"\A[a-z]{1,5}\Z").filter(
                lambda s: (
                    s
                    not in (
                        "theta",
                        "x",
                        "sin",
                        "cos",
                        "tan",
                        "exp",
                        "log",
                        "sqrt",
                        "abs",
                        "sign",
                        "sinh",
                        "cosh",
                        "tanh",
                        "pi",
                    )
                )
            )
        )
        param = draw(st.sampled_from(["unpenalized", "fixed_term"]))
        value = [f"{name}_dot**2"] if param == "unpenalized" else f"{name}_dot**2"
        return X, (None if param == "fixed_term" else tau), {param: value}, param
    raise AssertionError(kind)


KINDS = [
    "non-finite X",
    "non-finite tau",
    "text in X",
    "columns",
    "tau rows",
    "tau columns",
    "dimensions",
    "too few rows",
    "no motion",
    "parameter",
    "unknown term",
]


@SETTINGS
@given(data=st.data())
def test_invalid_input_always_raises_a_value_error(data):
    system = data.draw(st.sampled_from(list(SYSTEMS)), label="system")
    ds = dataset(system, True)
    kind = data.draw(st.sampled_from(KINDS), label="kind")
    X, tau, params, word = _corrupt(kind, ds.X, ds.tau, data.draw)
    with pytest.raises(ValueError) as err:
        fit(library(system), X, tau, **params)
    # a message of ours or scikit-learn's, never a numpy/pandas/torch exception type
    assert type(err.value).__module__.split(".")[0] in {
        "builtins",
        "lagsindy",
        "sklearn",
    }
    assert word in str(err.value)


# ----------------------------------------------------------------- units
@SETTINGS
@given(
    case=st.sampled_from(["forces", "fixed"]),
    noise=st.sampled_from([0.0, 0.02]),
    lam=st.sampled_from([1e-3, 1e-2]),
    threshold=st.sampled_from([0.02, 0.05, 0.1]),
    length_unit=log_scale(-3, 3),
    time_unit=log_scale(-2, 2),
    energy_unit=log_scale(-3, 3),
)
def test_a_change_of_units_rescales_the_coefficients(
    case, noise, lam, threshold, length_unit, time_unit, energy_unit
):
    """x (m -> mm: factor 1000), time and energy in other units.

    A term of degree a in (x, x_dot) and b in the velocities gets its coefficient
    multiplied by energy / length**a * time**b; the generalized force on x by
    energy / length. In case III the fixed term sets the scale, so only ratios to it
    are compared.
    """
    ref = reference("cart", case, noise, lam, threshold)
    data = dataset("cart", case == "forces", noise)
    X = data.X.copy()
    X[:, [0, 2, 4]] *= length_unit
    X[:, 2:4] /= time_unit
    X[:, 4:6] /= time_unit**2
    a, b = unit_exponents("cart").T
    factor = length_unit**-a * time_unit**b
    if case == "forces":
        tau = data.tau * energy_unit
        tau[:, 0] /= length_unit
        factor = factor * energy_unit
        est = fit(library("cart"), X, tau, lam=lam, threshold=threshold)
    else:
        est = fit(
            library("cart"), X, lam=lam, threshold=threshold, fixed_term="theta_dot**2"
        )
        factor = factor / factor[library("cart").index("theta_dot**2")]
    np.testing.assert_array_equal(est.support_, ref.support_)
    np.testing.assert_allclose(
        est.coef_ / factor, ref.coef_, rtol=1e-8, atol=1e-8 * np.abs(ref.coef_).max()
    )


# ----------------------------------------------------------------- sample order
@SETTINGS
@given(
    system=st.sampled_from(list(SYSTEMS)),
    case=st.sampled_from(["forces", "fixed", "search"]),
    noise=st.sampled_from([0.0, 0.02]),
    seed=st.integers(0, 2**32 - 1),
)
def test_permuting_samples_does_not_change_the_fit(system, case, noise, seed):
    """Rows are independent samples: only the summation order of the Gram changes."""
    assume(
        not (case == "search" and system == "cart")
    )  # the costly search: pendulum only
    data = dataset(system, case == "forces", noise)
    perm = np.random.default_rng(seed).permutation(len(data.X))
    lib = library(system)
    if case == "forces":
        ref = reference(system, "forces", noise)
        est = fit(lib, data.X[perm], data.tau[perm])
    elif case == "fixed":
        ref = reference(system, "fixed", noise)
        est = fit(lib, data.X[perm], fixed_term="theta_dot**2")
    else:
        ref = _search_reference(system, noise)
        est = fit(lib, data.X[perm])
        assert est.fixed_term_ == ref.fixed_term_
    np.testing.assert_array_equal(est.support_, ref.support_)
    np.testing.assert_allclose(
        est.coef_, ref.coef_, rtol=1e-10, atol=1e-10 * np.abs(ref.coef_).max()
    )


@functools.cache
def _search_reference(system, noise):
    return fit(library(system), dataset(system, False, noise).X)


# ----------------------------------------------------------------- gauge
CONSTANT_LIKE = [
    "1",
    "7.5",
    "pi",
    "cos(theta)**2 + sin(theta)**2",
    "theta_dot - theta_dot",
]
TOTAL_DERIVATIVES = [
    "theta_dot",
    "theta*theta_dot",
    "theta_dot*sin(theta)",
    "theta_dot*cos(theta)",
    "theta**2*theta_dot",
]


@SETTINGS
@given(
    extras=st.lists(
        st.sampled_from(CONSTANT_LIKE + TOTAL_DERIVATIVES),
        unique=True,
        min_size=1,
        max_size=5,
    ),
    positions=st.lists(st.integers(0, 10), min_size=5, max_size=5),
    active=st.booleans(),
    constant=st.floats(-1e3, 1e3),
    derivative=st.floats(-10, 10),
)
def test_constants_and_total_derivatives_change_nothing(
    extras, positions, active, constant, derivative
):
    """L and L + c + dF/dt have the same equations of motion (the Lagrangian's gauge).

    Constant-like candidates and total time derivatives are dropped by the library
    wherever they are listed, so the fit is bit-for-bit the one without them, and a
    Lagrangian written with them decomposes onto the same coefficients.
    """
    terms = list(PEND_TERMS)
    for term, pos in zip(extras, positions):
        terms.insert(pos % (len(terms) + 1), term)
    lib = CandidateLibrary.from_terms(["theta"], terms)
    base = library("pendulum")
    assert [str(t) for t in lib.terms_] == [str(t) for t in base.terms_]
    data = dataset("pendulum", active)
    params = {} if active else {"fixed_term": "theta_dot**2"}
    est = fit(lib, data.X, data.tau, **params)
    ref = reference("pendulum", "forces" if active else "fixed")
    assert est.coef_.tobytes() == ref.coef_.tobytes()
    # the gauge through decompose: c + a * d/dt(sin(theta)) adds nothing
    (th,), (thd,), _ = symbols_for(["theta"])
    shifted = PEND_TRUTH + sp.Float(constant) + sp.Float(derivative) * sp.cos(th) * thd
    c1, r1 = _truth_coefficients()
    c2, r2 = base.decompose(shifted)
    assert r1 < 1e-10 and r2 < 1e-10
    np.testing.assert_allclose(c2, c1, atol=1e-8)


PEND_TRUTH = single_pendulum().lagrangian


@functools.cache
def _truth_coefficients():
    return library("pendulum").decompose(PEND_TRUTH)


@SETTINGS
@given(
    fixed_term=st.sampled_from(sorted(CART_TRUTH)),
    lam=st.sampled_from([1e-3, 1e-2]),
    threshold=st.sampled_from([0.02, 0.05, 0.1]),
    seed=st.integers(0, 2**32 - 1),
    fraction=st.floats(0.5, 1.0),
)
def test_fixed_term_choice_rescales_passive_models(
    fixed_term, lam, threshold, seed, fraction
):
    """Passive data fix L only up to a factor: any true term can be fixed to 1.

    The learned coefficients are the true ones divided by the fixed term's, so the
    ratios between terms do not depend on the choice, and neither do the predicted
    accelerations (L and k L have the same equations of motion).
    """
    data = dataset("cart", False)
    n = len(data.X)
    X = data.X[
        np.sort(np.random.default_rng(seed).choice(n, int(fraction * n), replace=False))
    ]
    est = fit(library("cart"), X, lam=lam, threshold=threshold, fixed_term=fixed_term)
    learned = {est.term_names_[k]: est.coef_[k] for k in np.flatnonzero(est.coef_)}
    assert set(learned) == set(CART_TRUTH)
    assert learned[fixed_term] == 1.0
    for term, value in CART_TRUTH.items():
        assert learned[term] == pytest.approx(value / CART_TRUTH[fixed_term], rel=1e-6)
    np.testing.assert_allclose(
        est.predict_acceleration(X), X[:, 4:6], rtol=1e-5, atol=1e-5
    )
