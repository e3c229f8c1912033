"""MechanicalModel: equations of motion, numeric evaluation and mass checks."""

import pickle

import numpy as np
import pytest

from lagsindy import MechanicalModel, SingularMassMatrixError


def test_small_angle_pendulum_matches_cosine():
    model = MechanicalModel("0.5*theta_dot**2 + 9.81*cos(theta)", ["theta"])
    t = np.linspace(0, 5, 501)
    states = model.simulate([1e-3, 0.0], t)
    # the linearised solution; the nonlinear correction is ~ 1e-3 * (1e-3)**2 / 16 * w t
    np.testing.assert_allclose(
        states[:, 0], 1e-3 * np.cos(np.sqrt(9.81) * t), atol=1e-8
    )


def test_inverse_and_forward_dynamics_are_consistent():
    model = MechanicalModel(
        "0.75*x_dot**2 + 0.5*x_dot*theta_dot*cos(theta) + 0.25*theta_dot**2"
        " + 4.905*cos(theta)",
        ["x", "theta"],
    )
    rng = np.random.default_rng(0)
    q, qd, tau = rng.normal(size=(3, 40, 2))
    qdd = model.forward_dynamics(q, qd, tau)
    np.testing.assert_allclose(model.inverse_dynamics(q, qd, qdd), tau, atol=1e-12)


def test_indefinite_mass_matrix_raises_clear_error():
    # A "learned" model whose mass matrix [[1, cos], [cos, -0.4]] is indefinite.
    model = MechanicalModel(
        "0.5*x_dot**2 + x_dot*theta_dot*cos(theta) - 0.2*theta_dot**2 + 4.9*cos(theta)",
        ["x", "theta"],
        name="learned model",
    )
    with pytest.raises(
        SingularMassMatrixError, match=r"indefinite at t=0 .*theta=0\.3"
    ) as info:
        model.simulate([0.0, 0.3, 0.0, 0.0], np.linspace(0, 1, 5))
    assert info.value.t == 0.0
    np.testing.assert_allclose(info.value.q, [0.0, 0.3])
    assert np.any(info.value.eigenvalues < 0) and np.any(info.value.eigenvalues > 0)


def test_negative_definite_mass_matrix_is_valid():
    """A passive model learned up to a negative scale has the same motion."""
    pos = MechanicalModel("0.5*theta_dot**2 + 9.81*cos(theta)", ["theta"])
    neg = MechanicalModel("-0.5*theta_dot**2 - 9.81*cos(theta)", ["theta"])
    t = np.linspace(0, 3, 31)
    np.testing.assert_allclose(
        neg.simulate([1.0, 0.0], t), pos.simulate([1.0, 0.0], t), atol=1e-8
    )


def test_dissipation_and_forces_enter_equations():
    model = MechanicalModel(
        "0.5*x_dot**2 - 2*x**2",
        ["x"],
        dissipation="0.3*x_dot**2/2",
        forces=["-0.1*tanh(x_dot/0.01)"],
    )
    q, qd = np.array([[0.5]]), np.array([[2.0]])
    qdd = model.forward_dynamics(q, qd)
    np.testing.assert_allclose(qdd, [[-4 * 0.5 - 0.3 * 2.0 - 0.1 * np.tanh(200.0)]])
    states = model.simulate([1.0, 0.0], np.linspace(0, 10, 201))
    energy = model.energy(states[:, :1], states[:, 1:])
    assert np.all(np.diff(energy) <= 1e-9) and energy[-1] < 0.2 * energy[0]


def test_pickle_round_trip_keeps_equations():
    model = MechanicalModel("0.5*theta_dot**2 + 9.81*cos(theta)", ["theta"])
    model.simulate([0.1, 0.0], [0.0, 0.1])  # compile the lambdified code first
    copy = pickle.loads(pickle.dumps(model))
    np.testing.assert_allclose(
        copy.simulate([0.1, 0.0], [0.0, 0.1]), model.simulate([0.1, 0.0], [0.0, 0.1])
    )


def test_equation_text_and_errors():
    model = MechanicalModel(
        "0.123456*theta_dot**2 + 9.81*cos(theta)",
        ["theta"],
        dissipation="0.1*theta_dot**2",
    )
    text = model.equation(3)
    assert "L = 0.123*theta_dot**2" in text and "D = 0.1*theta_dot**2" in text
    with pytest.raises(ValueError, match="one entry per coordinate"):
        MechanicalModel("x_dot**2", ["x"], forces=["0", "0"])
    with pytest.raises(ValueError, match="x0"):
        model.simulate([0.0], [0, 1])
    with pytest.raises(ValueError, match="increasing"):
        model.simulate([0.0, 0.0], [1, 0])
