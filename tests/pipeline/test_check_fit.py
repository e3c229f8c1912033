"""The fit's checks (lagsindy.pipeline.check_fit) on forces that no Lagrangian
explains: the right forces pass silently, negated forces are named by the mass
matrix's sign, wrong ones by the residual, and the default library says when it
cannot couple coordinates."""

import warnings

import numpy as np
import pytest

from lagsindy import LagrangianSINDy
from lagsindy.systems import double_pendulum, make_dataset


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
    assert est.residual_ < 1.8e-7  # measured: 3.5e-8
    assert est.mass_check_.negative == 0.0
    assert caught == []


def test_negated_forces_say_the_kinetic_energy_is_negative(double):
    """-tau fits -L exactly: the residual says nothing, the mass matrix does."""
    est, caught = _fit_recorded(double, -double.tau)
    assert est.residual_ < 1.8e-7  # measured: 3.5e-8, as with the right sign
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


def test_the_fits_warnings_point_at_the_users_line():
    """Warnings raised deep in the fit (the probes, the identifiability check, the
    fallback to the strong form) name the line that called ``fit``, not a line of
    lagsindy or of scikit-learn's wrapper around ``fit``."""
    from lagsindy.systems import cart_pendulum

    system = cart_pendulum().with_damping(viscous={"x": 3.0})
    data = make_dataset(
        system, 6, 4.0, excitation="sincos", noise=1e-3, protocol="sensor",
        random_state=0,
    )  # fmt: skip
    est = LagrangianSINDy(system.paper_library())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est.fit(data.X, data.tau, groups=data.groups)
    kinds = {w.category.__name__ for w in caught}
    assert "UnmodelledForceWarning" in kinds  # replayed from the joint fit
    assert [w.filename for w in caught] == [__file__] * len(caught), [
        (w.category.__name__, w.filename, w.lineno) for w in caught
    ]
