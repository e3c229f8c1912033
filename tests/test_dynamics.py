import pickle

import numpy as np
import pytest

from lagsindy import MechanicalModel, SingularMassMatrixError, rollout_error


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
        "0.75*x_dot**2 + 0.5*x_dot*theta_dot*cos(theta) + 0.25*theta_dot**2 + 4.905*cos(theta)",
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


def test_mass_matrix_turning_singular_midway_stops_with_time_and_state():
    # M = cos(theta): fine at theta = 0, singular when the swing reaches pi/2.
    model = MechanicalModel("0.5*theta_dot**2*cos(theta)", ["theta"])
    with pytest.raises(SingularMassMatrixError) as info:
        model.simulate([0.0, 3.0], np.linspace(0, 5, 51))
    assert 0.0 < info.value.t < 5.0
    assert abs(abs(info.value.q[0]) - np.pi / 2) < 0.05
    assert "t=" in str(info.value) and "theta=" in str(info.value)


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


def test_input_matrix_and_sampled_input():
    model = MechanicalModel(
        "0.5*x_dot**2 + 0.5*y_dot**2", ["x", "y"], input_matrix=[[1.0], [0.0]]
    )
    t = np.linspace(0, 1, 101)
    u = np.cos(t)[:, None]
    states = model.simulate([0, 0, 0, 0], t, tau=u)
    np.testing.assert_allclose(
        states[:, 0], 1 - np.cos(t), atol=1e-4
    )  # linear interpolation
    np.testing.assert_allclose(states[:, 1], 0.0)
    exact = model.simulate([0, 0, 0, 0], t, tau=lambda tt, x: np.array([np.cos(tt)]))
    np.testing.assert_allclose(exact[:, 0], 1 - np.cos(t), atol=1e-8)
    with pytest.raises(ValueError, match="shape"):
        model.simulate([0, 0, 0, 0], t, tau=np.zeros((101, 2)))


def test_batch_simulation_matches_single():
    model = MechanicalModel("0.5*theta_dot**2 + 9.81*cos(theta)", ["theta"])
    t = np.linspace(0, 2, 21)
    x0 = np.array([[0.5, 0.0], [1.0, 0.5], [-2.0, 0.0]])
    batch = model.simulate(x0, t)
    for i in range(3):
        np.testing.assert_allclose(batch[i], model.simulate(x0[i], t), atol=1e-7)


def test_pickle_round_trip_keeps_equations():
    model = MechanicalModel("0.5*theta_dot**2 + 9.81*cos(theta)", ["theta"])
    model.simulate([0.1, 0.0], [0.0, 0.1])  # compile the lambdified code first
    copy = pickle.loads(pickle.dumps(model))
    np.testing.assert_allclose(
        copy.simulate([0.1, 0.0], [0.0, 0.1]), model.simulate([0.1, 0.0], [0.0, 0.1])
    )


def test_rollout_error_reports_divergence_and_failure():
    true = MechanicalModel("0.5*theta_dot**2 + 9.81*cos(theta)", ["theta"])
    close = MechanicalModel("0.5*theta_dot**2 + 9.8*cos(theta)", ["theta"])
    broken = MechanicalModel(
        "-0.5*theta_dot**2*sin(theta) + 9.81*cos(theta)", ["theta"]
    )
    t = np.linspace(0, 5, 101)
    out = rollout_error(true, close, [1.0, 0.0], t)
    assert 1e-4 < out["max_abs_q"] < 0.1
    bad = rollout_error(true, broken, [-1.0, 0.0], t)  # M = -sin(theta) flips sign at 0
    assert bad["max_abs_q"] == np.inf and "singular" in bad["error"]


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


def _cart_with_sampled_input():
    from lagsindy.systems import cart_pendulum

    model = cart_pendulum()
    t = np.arange(0.0, 0.3, 1e-3)  # a 1 kHz input with a kink at every sample
    u = np.random.default_rng(0).normal(size=(t.size, model.n_inputs))
    return model, t, u


def test_sampled_input_steps_end_at_samples_and_match_a_tight_reference():
    model, t, u = _cart_with_sampled_input()
    x0 = [0.1, 0.2, 0.0, 0.0]
    got = model.simulate(x0, t, u)
    # Radau through solve_ivp crosses the kinks with tight tolerances instead.
    ref = model.simulate(x0, t, u, method="Radau", rtol=1e-12, atol=1e-12)
    assert np.abs(got - ref).max() < 5e-10  # measured 5.8e-11


def test_scalar_and_batched_right_hand_sides_agree():
    """One trajectory (Python-float right-hand side) against a batch of one (numpy)."""
    model, t, u = _cart_with_sampled_input()
    x0 = np.array([0.1, 0.2, 0.3, -0.1])
    single = model.simulate(x0, t, u)
    batch = model.simulate(x0[None], t, u[None])[0]
    np.testing.assert_allclose(single, batch, rtol=0, atol=1e-14)  # measured 2.2e-16
    free = model.simulate(x0, t[:50])
    np.testing.assert_allclose(free, model.simulate(x0[None], t[:50])[0], atol=1e-12)
