"""Fits recover the true models of the benchmark systems: case I and case III
(fixed term, automatic choice, mass normalization, ties), degenerate data that
must be reported, undriven light links, cyclic undriven coordinates, and
dissipation that must stay non-negative."""

import warnings

import numpy as np
import pytest

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy
from lagsindy.estimator import IdentifiabilityWarning
from lagsindy.formulation import make_formulation
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    make_dataset,
    single_pendulum,
    spherical_pendulum,
)


def _learned(est):
    names = est.term_names_
    return {names[k]: est.coef_[k] for k in np.flatnonzero(est.coef_)}


def test_cart_pendulum_case_I_recovers_true_terms(cart_active):
    """Acceptance: 55-term library, tau = a sin(wt) + b cos(wt), noise-free data."""
    system = cart_pendulum()
    lib = system.paper_library()
    assert len(lib.candidates_) == 55
    est = LagrangianSINDy(lib).fit(cart_active.X, cart_active.tau)
    learned = _learned(est)
    truth = {
        "x_dot**2": 0.75,
        "theta_dot**2": 0.25,
        "theta_dot*x_dot*cos(theta)": 0.5,
        "cos(theta)": 4.905,
    }
    assert set(learned) == set(truth)
    for term, value in truth.items():
        # measured 2.5e-5 at most
        assert learned[term] == pytest.approx(value, rel=1.3e-4), term
    assert est.case_ == "forces" and est.fixed_term_ is None
    assert est.score(cart_active.X, cart_active.tau) > 0.999999


def test_single_pendulum_case_I(single_active):
    est = LagrangianSINDy(single_pendulum().paper_library()).fit(
        single_active.X, single_active.tau
    )
    learned = _learned(est)
    assert set(learned) == {"theta_dot**2", "cos(theta)"}
    assert learned["theta_dot**2"] == pytest.approx(0.5, rel=3e-4)  # measured 6e-5
    assert learned["cos(theta)"] == pytest.approx(9.81, rel=1e-7)  # measured 1.8e-8


def test_single_pendulum_case_III_ratio(single_passive):
    est = LagrangianSINDy(single_pendulum().paper_library(), fixed_term="theta_dot**2")
    est.fit(single_passive.X)
    learned = _learned(est)
    assert est.case_ == "fixed" and est.fixed_term_ == "theta_dot**2"
    assert set(learned) == {"theta_dot**2", "cos(theta)"}
    assert learned["theta_dot**2"] == 1.0
    assert learned["cos(theta)"] / learned["theta_dot**2"] == pytest.approx(
        19.62, rel=3.2e-4
    )  # measured 6.3e-5


def test_case_III_chooses_fixed_term_automatically():
    data = make_dataset(
        double_pendulum(), n_trajectories=30, excitation=None, random_state=3
    )
    est = LagrangianSINDy(double_pendulum().paper_library(), random_state=0).fit(data.X)
    learned = _learned(est)
    assert est.fixed_term_ in learned and learned[est.fixed_term_] == 1.0
    scale = learned["theta1_dot**2"]
    want = {
        "theta1_dot**2": 1.0,
        "theta2_dot**2": 0.5,
        "cos(theta1)": 19.62,
        "cos(theta2)": 9.81,
        "theta1_dot*theta2_dot*cos(theta1)*cos(theta2)": 1.0,
        "theta1_dot*theta2_dot*sin(theta1)*sin(theta2)": 1.0,
    }
    assert set(learned) == set(want)
    for term, value in want.items():
        assert learned[term] / scale == pytest.approx(value, rel=1.3e-4)  # 2.5e-5
    assert est.score(data.X) > 0.9999


def test_mass_normalization_avoids_the_near_null_lagrangian():
    """Fixing theta_dot**2 = 1 lets theta_dot**2 * (cos, sin**2, theta**2) cancel it.

    With noisy passive data the fixed-term fit then prefers a Lagrangian that nearly
    vanishes on the data; fixing the mean trace of the mass matrix rules it out.
    """
    data = make_dataset(
        single_pendulum(),
        n_trajectories=10,
        excitation=None,
        noise=0.05,
        random_state=0,
    )
    terms = [
        "theta_dot**2",
        "theta_dot**2*cos(theta)",
        "theta_dot**2*sin(theta)**2",
        "cos(theta)",
        "theta_dot**2*theta**2",
        "theta_dot**2*cos(theta)**2",
    ]
    lib = CandidateLibrary.from_terms(["theta"], terms)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pinned = LagrangianSINDy(
            lib, fixed_term="theta_dot**2", formulation="strong"
        ).fit(data.X)
    mass = LagrangianSINDy(lib, fixed_term="mass", formulation="strong").fit(data.X)
    learned = _learned(mass)
    assert mass.normalization_ == "mass" and mass.fixed_term_ == "theta_dot**2"
    assert set(learned) == {"theta_dot**2", "cos(theta)"}
    assert learned["theta_dot**2"] == 1.0
    assert learned["cos(theta)"] == pytest.approx(19.62, rel=0.02)
    assert mass.score(data.X) > 0.99 > pinned.score(data.X)
    # The automatic search considers the mass normalization too and picks it here.
    auto = LagrangianSINDy(lib, formulation="strong").fit(data.X)
    assert auto.normalization_ == "mass"
    np.testing.assert_allclose(auto.coef_, mass.coef_)


def test_case_III_search_breaks_near_ties_towards_the_sparsest_model():
    """Among candidates within 10 % of the best unexplained variance, fewest terms win.

    Measured (noisy passive pendulum, weak form): the search picks the 2-term
    Lagrangian (theta_dot**2, cos(theta)), unexplained acceleration variance
    0.009301; fixing sin(theta)**2 gives a 5-term model that fits slightly better,
    0.009278 (ratio 0.9976, inside the 1.1 tie band). A tie-break towards the
    densest model picks the 5-term one.
    """
    data = make_dataset(
        single_pendulum(),
        n_trajectories=10,
        excitation=None,
        noise=0.05,
        random_state=0,
    )
    lib = single_pendulum().paper_library()
    auto = LagrangianSINDy(lib, formulation="weak", random_state=0)
    auto.fit(data.X, groups=data.groups)
    dense = LagrangianSINDy(
        lib, formulation="weak", fixed_term="sin(theta)**2", random_state=0
    ).fit(data.X, groups=data.groups)
    # the search keeps the sparse truth
    learned = _learned(auto)
    assert set(learned) == {"theta_dot**2", "cos(theta)"}
    ratio = learned["cos(theta)"] / learned["theta_dot**2"]
    assert ratio == pytest.approx(19.62, rel=0.03)  # measured 20.09 (noise 0.05)
    # though a denser candidate fits a little better, within the tie band
    assert np.count_nonzero(dense.coef_) == 5
    worse, better = 1 - auto.score(data.X), 1 - dense.score(data.X)
    assert worse / 1.1 < better < worse


def test_spherical_passive_needs_the_right_fixed_term():
    """theta_dot**2 alone is fit by a theta-only Lagrangian; the search avoids it."""
    data = make_dataset(
        spherical_pendulum(), n_trajectories=30, excitation=None, random_state=4
    )
    lib = spherical_pendulum().paper_library()
    est = LagrangianSINDy(lib, random_state=0).fit(data.X)
    learned = _learned(est)
    ratio = {k: v / learned["theta_dot**2"] for k, v in learned.items()}
    assert set(ratio) == {"theta_dot**2", "phi_dot**2*sin(theta)**2", "cos(theta)"}
    assert ratio["cos(theta)"] == pytest.approx(19.62, rel=6e-5)  # measured 1.1e-5
    # With the paper's prior (cos(theta) known, unpenalised) theta_dot**2 works too
    est2 = LagrangianSINDy(
        lib, fixed_term="theta_dot**2", unpenalized=["cos(theta)"]
    ).fit(data.X)
    assert set(_learned(est2)) == set(ratio)


def test_constant_input_degeneracy_is_reported():
    """The paper's spherical input (constant on phi) is a linear potential in phi."""
    data = make_dataset(
        spherical_pendulum(), n_trajectories=10, excitation="paper", random_state=5
    )
    with pytest.warns(IdentifiabilityWarning, match="phi"):
        LagrangianSINDy(spherical_pendulum().paper_library()).fit(data.X, data.tau)


@pytest.mark.slow  # ~20 s of the default suite's 5-minute budget
def test_degenerate_case_III_model_is_flagged():
    """Fixing theta1_dot**2 on a triple pendulum yields a theta1-only Lagrangian."""
    from lagsindy.systems import triple_pendulum

    s = triple_pendulum()
    data = make_dataset(s, n_trajectories=20, excitation=None, random_state=0)
    with pytest.warns(UserWarning, match=r"singular or indefinite.*theta2"):
        LagrangianSINDy(
            s.paper_library(), fixed_term="theta1_dot**2", unpenalized=["cos(theta1)"]
        ).fit(data.X)


def test_fitted_dissipation_is_never_negative():
    """An undamped pendulum fitted with viscous and Coulomb candidates and noise:
    the dissipation coefficients are >= 0 (they used to come out slightly negative)."""
    data = make_dataset(
        single_pendulum(),
        n_trajectories=10,
        excitation="paper",
        noise=0.02,
        random_state=3,
    )
    dlib = DissipationLibrary(kinds=("viscous", "coulomb", "drag"))
    for form in ("strong", "weak"):
        est = LagrangianSINDy(
            single_pendulum().paper_library(),
            dissipation=dlib,
            formulation=make_formulation(form, dt=0.01),
        ).fit(data.X, data.tau, groups=data.groups)
        assert np.all(est.dissipation_coef_ >= 0), (form, est.dissipation_coef_)


def _ratios(est, names):
    c = dict(zip(est.term_names_, est.coef_))
    return {n: c[n] / c["theta_dot**2"] for n in names}


@pytest.mark.parametrize(
    "mass, damping, amplitude",
    [(0.03, 0.5, 1.0), (0.05, 0.2, 2.0), (0.02, 1.0, 1.0)],
)
def test_light_undriven_link_keeps_its_terms(mass, damping, amplitude):
    """A pendulum of 2-5 % of the cart's mass on a damped cart, force on the cart
    only, noisy data, defaults: the link's own terms stay, with the right ratios."""
    from lagsindy.systems import cart_pendulum

    system = cart_pendulum(cart_mass=1.0, mass=mass).with_damping(
        viscous={"x": damping}
    )
    data = make_dataset(
        system,
        n_trajectories=10,
        excitation="sincos",
        amplitude=amplitude,
        noise=0.01,
        random_state=0,
    )
    est = LagrangianSINDy(
        system.paper_library(), dissipation=DissipationLibrary(["viscous"])
    ).fit(data.X, data.tau, groups=data.groups)
    assert est.formulation_ == "weak"
    assert set(est.term_names_[est.support_]) == {
        "x_dot**2",
        "theta_dot*x_dot*cos(theta)",
        "theta_dot**2",
        "cos(theta)",
    }
    truth = dict(zip(est.term_names_, system.true_coefficients(est.library_)))
    names = ["cos(theta)", "theta_dot*x_dot*cos(theta)", "x_dot**2"]
    expected = {n: truth[n] / truth["theta_dot**2"] for n in names}
    for n, r in _ratios(est, names).items():
        # measured at most 0.9 % (x_dot**2 / theta_dot**2 at mass 0.02)
        assert r == pytest.approx(expected[n], rel=0.03), n
    assert est.mass_check_.ok


def test_undriven_cyclic_cart_under_a_torque_keeps_every_term():
    """Torque and damping on theta, the cart free and undriven (x cyclic): the
    homogeneous x equation used to collapse the cart's terms (L = 0 reported)."""
    from lagsindy.systems import cart_pendulum
    from lagsindy.systems.base import System

    base = cart_pendulum(mass=0.5)
    system = System(
        base.lagrangian,
        ["x", "theta"],
        angles=["theta"],
        initial_ranges=base.initial_ranges,
        input_matrix=[[0.0], [1.0]],
        library=base.paper_library,
        name="cart under a joint torque",
    ).with_damping(viscous={"theta": 0.3})
    data = make_dataset(
        system, n_trajectories=10, excitation="sincos", noise=0.02, random_state=0
    )
    est = LagrangianSINDy(
        system.paper_library(), dissipation=DissipationLibrary(["viscous"])
    ).fit(data.X, data.tau, groups=data.groups)
    assert est.formulation_ == "weak"
    truth = system.true_coefficients(est.library_)
    assert set(est.term_names_[est.support_]) == set(est.term_names_[truth != 0])
    # measured 0.8 % (x_dot**2, coupling), 0.1 % (theta terms), 0.3 % damping
    np.testing.assert_allclose(est.coef_[truth != 0], truth[truth != 0], rtol=0.03)
    assert est.dissipation_coef_.max() == pytest.approx(0.3, rel=0.015)
    assert est.mass_check_.ok
