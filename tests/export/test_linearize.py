"""Linearization: exact Jacobians, zero-order hold, and the equilibrium check."""

import warnings

import numpy as np
import pytest
from scipy.signal import cont2discrete

from lagsindy.export import (
    EQUILIBRIUM_RTOL,
    discretize,
    export_source,
    linearize,
    load_python,
)
from lagsindy.systems import cart_pendulum, single_pendulum, triple_pendulum

UPRIGHT = np.array([0.0, np.pi, 0.0, 0.0])


def test_cart_pendulum_upright_in_closed_form():
    # M(pi) = [[1.5, -0.5], [-0.5, 0.5]], M^-1 = [[1, 1], [1, 3]], d r_theta/d theta
    # = -4.905: d qdd / d theta = M^-1 [0, 4.905] = [4.905, 14.715], B = M^-1 [1, 0].
    lin = linearize(cart_pendulum(), UPRIGHT, [0.0])
    expected = np.zeros((4, 4))
    expected[0, 2] = expected[1, 3] = 1.0
    expected[2, 1], expected[3, 1] = 4.905, 14.715
    np.testing.assert_allclose(lin.A, expected, atol=1e-13)
    np.testing.assert_allclose(lin.B.ravel(), [0.0, 0.0, 1.0, 1.0], atol=1e-15)
    assert lin.residual < 1e-15 and lin.Ad is None and lin.coordinates == ["x", "theta"]


def test_jacobians_equal_finite_differences_of_the_export():
    system = triple_pendulum().with_damping({"theta1": 0.3}, {"theta2": 0.1})
    python = load_python(export_source(system, "python"))
    rng = np.random.default_rng(5)
    x = rng.uniform(0.5, 1.5, 6) * rng.choice([-1, 1], 6)
    u = rng.uniform(-1, 1, 3)
    lin = linearize(system, x, u, warn=False)  # not an equilibrium: any state
    h = 1e-6
    fd_a = np.stack(
        [
            (
                python.state_derivative(x + h * e, u)
                - python.state_derivative(x - h * e, u)
            )
            / (2 * h)
            for e in np.eye(6)
        ],
        axis=1,
    )
    fd_b = np.stack(
        [
            (
                python.state_derivative(x, u + h * e)
                - python.state_derivative(x, u - h * e)
            )
            / (2 * h)
            for e in np.eye(3)
        ],
        axis=1,
    )
    # measured 4.5e-10 (A) and 8.2e-10 (B) relative: the differences' error
    assert np.abs(lin.A - fd_a).max() < 5e-9 * np.abs(lin.A).max()
    assert np.abs(lin.B - fd_b).max() < 5e-9 * np.abs(lin.B).max()
    np.testing.assert_allclose(lin.f_eq, python.state_derivative(x, u), rtol=1e-14)


def test_jacobians_equal_casadis():
    ca = pytest.importorskip("casadi")
    from lagsindy.export import to_casadi

    system = triple_pendulum().with_damping({"theta1": 0.3}, {"theta2": 0.1})
    f = to_casadi(system)
    xs, us = ca.SX.sym("x", 6), ca.SX.sym("u", 3)
    rhs = f.state_derivative(xs, us)
    jac = ca.Function("J", [xs, us], [ca.jacobian(rhs, xs), ca.jacobian(rhs, us)])
    x = np.array([0.4, -1.0, 2.0, 0.7, -0.6, 1.1])
    u = np.array([0.2, 0.0, -0.4])
    lin = linearize(system, x, u, warn=False)
    a, b = (np.array(j) for j in jac(x, u))
    # measured 3.7e-16 (A) and 2.2e-16 (B) relative
    assert np.abs(lin.A - a).max() < 2e-15 * np.abs(a).max()
    assert np.abs(lin.B - b).max() < 2e-15 * np.abs(b).max()


def test_zero_order_hold_equals_scipy():
    lin = linearize(cart_pendulum(), UPRIGHT, [0.0], dt=0.02)
    ad, bd, *_ = cont2discrete((lin.A, lin.B, np.eye(4), np.zeros((4, 1))), 0.02)
    np.testing.assert_allclose(lin.Ad, ad, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(lin.Bd, bd, rtol=1e-13, atol=1e-15)
    assert lin.dt == 0.02
    with pytest.raises(ValueError, match="dt must be a positive"):
        discretize(lin.A, lin.B, 0.0)


def test_an_input_that_holds_the_state_is_an_equilibrium():
    theta = 0.5
    torque = 9.81 * np.sin(theta)  # holds the pendulum at 0.5 rad
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lin = linearize(single_pendulum(), [theta, 0.0], [torque])
    assert lin.residual < 1e-15
    np.testing.assert_allclose(lin.A, [[0.0, 1.0], [-9.81 * np.cos(theta), 0.0]])


@pytest.mark.parametrize("factor", [0.99, 1.01])
def test_the_equilibrium_warning_threshold(factor):
    # residual = 1.0000014 d at theta = pi + d: just below the threshold stays
    # quiet, just above warns
    d = factor * EQUILIBRIUM_RTOL
    x = UPRIGHT + [0.0, d, 0.0, 0.0]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        lin = linearize(cart_pendulum(), x, [0.0])
    warned = [w for w in caught if "not an equilibrium" in str(w.message)]
    assert (lin.residual > EQUILIBRIUM_RTOL) == (factor > 1)
    assert len(warned) == (1 if factor > 1 else 0)
    if warned:
        assert warned[0].filename == __file__


def test_bad_points_raise():
    with pytest.raises(ValueError, match="x_eq must have 4 entries"):
        linearize(cart_pendulum(), [0.0, 1.0])
    with pytest.raises(ValueError, match="u_eq must have 1 entries"):
        linearize(cart_pendulum(), UPRIGHT, [0.0, 0.0])
    with pytest.raises(ValueError, match="finite"):
        linearize(cart_pendulum(), [0.0, np.nan, 0.0, 0.0])


def test_coefficients_enter_to_the_last_bit():
    import sympy as sp

    from lagsindy import MechanicalModel

    # a learned model's coefficients are sympy Floats made from Python floats
    c, k = 0.12345678901234568, 9.876543210987654  # 17 significant digits
    theta, theta_dot = sp.symbols("theta theta_dot", real=True)
    lagrangian = sp.Float(c) * theta_dot**2 + sp.Float(k) * sp.cos(theta)
    model = MechanicalModel(lagrangian, ["theta"])
    lin = linearize(model, [0.0, 0.0])
    # the mass 2c enters exactly (written with 15 digits, it is 6 units in the
    # last place off); LAPACK divides by way of the pivot's reciprocal: 1 ulp
    assert lin.B[1, 0] == 1 / (2 * c)
    assert abs(lin.A[1, 0] + k / (2 * c)) <= 2 * np.spacing(k / (2 * c))
