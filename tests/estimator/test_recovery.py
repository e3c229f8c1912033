"""Fits recover the true models of systems that are hard to fit: undriven light
links, cyclic undriven coordinates, and dissipation that must stay non-negative."""

import numpy as np
import pytest

from lagsindy import DissipationLibrary, LagrangianSINDy
from lagsindy.systems import make_dataset, single_pendulum


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
            formulation=form,
            dt=0.01,
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
