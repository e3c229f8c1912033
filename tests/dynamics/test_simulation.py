"""Simulation of mechanical models: inputs, batches, steppers, failures."""

import numpy as np
import pytest
from scipy.integrate import DOP853

from lagsindy import MechanicalModel, SingularMassMatrixError, rollout_error
from lagsindy.dynamics import simulation, steppers


def test_mass_matrix_turning_singular_midway_stops_with_time_and_state():
    # M = cos(theta): fine at theta = 0, singular when the swing reaches pi/2.
    model = MechanicalModel("0.5*theta_dot**2*cos(theta)", ["theta"])
    with pytest.raises(SingularMassMatrixError) as info:
        model.simulate([0.0, 3.0], np.linspace(0, 5, 51))
    assert 0.0 < info.value.t < 5.0
    assert abs(abs(info.value.q[0]) - np.pi / 2) < 0.05
    assert "t=" in str(info.value) and "theta=" in str(info.value)


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


@pytest.mark.parametrize("system", ["single_pendulum", "cart_pendulum"])
@pytest.mark.parametrize(
    "method, dt, bound",
    [
        ("DOP853", 1e-3, 1e-13),  # measured 1.1e-14 (single), 3.8e-15 (cart)
        ("RK45", 2e-2, 5e-9),  # several steps per sample: measured 1.5e-9, 1.8e-9
    ],
)
def test_float_integrator_matches_a_fine_scipy_reference(system, method, dt, bound):
    """The generated Python-float Runge-Kutta path against scipy's own DOP853 stepper.

    The reference takes at least 4 steps per sample (max_step 2.5e-4, rtol 1e-10) with
    scipy's solver class; Radau at rtol 1e-10 is itself off by 4e-7 here (1.4e-9 at
    1e-12), so it would not resolve these errors.
    """
    from lagsindy import systems

    model = getattr(systems, system)()
    x0 = [1.0, 0.0] if model.n_dof == 1 else [0.1, 0.2, 0.0, 0.0]
    t = np.arange(0.0, 1.0, dt)
    u = 2 * np.sin(2 * np.pi * 1.3 * t)[:, None] * np.ones((1, model.n_inputs))
    assert (
        simulation.float_rhs(model, u, t) is not None
    )  # the fast path is the one tested
    got = model.simulate(x0, t, u, method=method)
    rhs = simulation.scalar_rhs(model, u, t, True, None, np.ones(1), {})
    ref, status, _ = steppers.integrate_between(
        DOP853, rhs, t, np.asarray(x0, dtype=float), 1e-10, 1e-10, 2.5e-4
    )
    assert status == 0
    assert np.abs(got - ref).max() < bound


def test_float_integrator_reports_a_singular_mass_matrix():
    """A zero determinant mid-run in the float path ends in the mass-matrix error."""
    # M = cos(theta), singular when a constant push swings theta to pi/2.
    model = MechanicalModel(
        "0.5*theta_dot**2*cos(theta)", ["theta"], input_matrix=[[1.0]]
    )
    t = np.arange(0.0, 5.0, 1e-3)
    assert simulation.float_rhs(model, np.ones(t.size), t) is not None
    with pytest.raises(SingularMassMatrixError) as info:
        model.simulate([0.0, 3.0], t, np.ones(t.size))
    assert abs(abs(info.value.q[0]) - np.pi / 2) < 0.05
