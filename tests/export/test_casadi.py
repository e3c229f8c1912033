"""CasADi functions: exact Jacobians, every quantity, a clear error without CasADi."""

import builtins

import numpy as np
import pytest

from lagsindy.export import export_source, load_python, to_casadi
from lagsindy.systems import cart_pendulum, triple_pendulum

# The acceptance bound is 1e-6. Central differences with step h = 1e-6 agree with
# CasADi's exact Jacobian to 4.8e-10 (cart) and 1.4e-9 (triple pendulum) relative to
# its largest entry (measured); the test holds that size.
FD_RTOL = 1e-8


def _damped(system):
    first, last = system.coordinates[0], system.coordinates[-1]
    return system.with_damping({first: 0.2}, {last: 0.3})


def _central_differences(f, x, h=1e-6):
    cols = []
    for k in range(x.size):
        step = np.zeros_like(x)
        step[k] = h
        cols.append((f(x + step) - f(x - step)) / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("make", [cart_pendulum, triple_pendulum])
def test_jacobians_equal_finite_differences(make):
    ca = pytest.importorskip("casadi")
    system = _damped(make())
    f = to_casadi(system)
    n, m = system.n_dof, system.n_inputs
    x_sym, u_sym = ca.SX.sym("x", 2 * n), ca.SX.sym("u", m)
    acc = f.forward_dynamics(x_sym, u_sym)
    jac = ca.Function(
        "J", [x_sym, u_sym], [ca.jacobian(acc, x_sym), ca.jacobian(acc, u_sym)]
    )
    rng = np.random.default_rng(4)
    worst = 0.0
    for _ in range(5):
        # |velocities| >= 0.5: the Coulomb tanh(v / 0.01) is steep near v = 0
        x = rng.uniform(0.5, 2.0, 2 * n) * rng.choice([-1, 1], 2 * n)
        u = rng.uniform(-1, 1, m)
        jx, ju = (np.array(j) for j in jac(x, u))

        def of_x(xx, u=u):
            return np.array(f.forward_dynamics(xx, u)).ravel()

        def of_u(uu, x=x):
            return np.array(f.forward_dynamics(x, uu)).ravel()

        for exact, approx in (
            (jx, _central_differences(of_x, x)),
            (ju, _central_differences(of_u, u)),
        ):
            worst = max(worst, np.abs(exact - approx).max() / np.abs(exact).max())
    assert worst < FD_RTOL


def test_every_quantity_matches_the_python_export():
    pytest.importorskip("casadi")
    system = _damped(triple_pendulum())
    f = to_casadi(system, name="triple")
    python = load_python(export_source(system, "python"))
    q, qd, qdd = np.array([0.1, 0.5, -1.0]), np.array([1.0, -2.0, 0.5]), np.ones(3)
    u = np.array([0.3, -0.1, 0.2])
    x = np.concatenate([q, qd])
    np.testing.assert_allclose(
        np.array(f.state_derivative(x, u)).ravel(),
        python.state_derivative(x, u),
        rtol=1e-14,
    )
    np.testing.assert_allclose(
        np.array(f.mass_matrix(q, qd)), python.mass_matrix(q, qd), rtol=1e-15
    )
    assert float(f.energy(q, qd)) == pytest.approx(
        float(python.energy(q, qd)), rel=1e-15
    )
    np.testing.assert_allclose(
        np.array(f.inverse_dynamics(q, qd, qdd)).ravel(),
        python.inverse_dynamics(q, qd, qdd),
        rtol=1e-14,
    )
    assert f.forward_dynamics.name() == "triple_forward_dynamics"
    assert (f.n_dof, f.n_inputs, f.coordinates) == (3, 3, system.coordinates)


def test_an_input_matrix_selects_the_driven_coordinates():
    pytest.importorskip("casadi")
    f = to_casadi(cart_pendulum(), input_matrix=[[1.0], [0.0]])
    assert f.forward_dynamics.size1_in(1) == 1
    python = load_python(export_source(cart_pendulum(), "python"))
    x = np.array([0.0, 2.0, 0.1, 0.3])
    np.testing.assert_allclose(
        np.array(f.forward_dynamics(x, 1.5)).ravel(),
        python.forward_dynamics(x, 1.5),
        rtol=1e-14,
    )


def test_without_casadi_the_error_says_how_to_install_it(monkeypatch):
    real_import = builtins.__import__

    def no_casadi(name, *args, **kwargs):
        if name == "casadi" or name.startswith("casadi."):
            raise ImportError("No module named 'casadi'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_casadi)
    with pytest.raises(ImportError, match="pip install casadi"):
        to_casadi(cart_pendulum())
