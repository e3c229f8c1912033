"""The exported Python module: standalone, vectorized, exact, with its provenance."""

import subprocess
import sys

import numpy as np
import pytest

from lagsindy import MechanicalModel, __version__, load_model, save_model
from lagsindy.export import export_model, export_source, load_python
from lagsindy.systems import cart_pendulum

from ._models import COULOMB, VISCOUS, true_estimator


@pytest.fixture(scope="module")
def cart(tmp_path_factory):
    est, path = true_estimator("cart_pendulum", True, tmp_path_factory.mktemp("m"))
    module = load_python(export_source(est, "python", input_matrix=[[1.0], [0.0]]))
    return est, module


def test_the_module_runs_without_lagsindy(tmp_path):
    path = export_model(cart_pendulum(), tmp_path / "cartpole.py")
    script = (
        "import sys, importlib.util\n"
        "sys.modules['lagsindy'] = None  # importing lagsindy now fails\n"
        f"spec = importlib.util.spec_from_file_location('cartpole', {str(path)!r})\n"
        "m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m)\n"
        "print(repr(float(m.forward_dynamics([0.0, 3.0, 0.5, -1.0], [2.0])[1])))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path
    )
    assert done.returncode == 0, done.stderr
    system = cart_pendulum()
    expected = system.forward_dynamics([0.0, 3.0], [0.5, -1.0], [[2.0, 0.0]])[0, 1]
    assert float(done.stdout) == pytest.approx(expected, rel=1e-14)


def test_leading_axes_and_input_shapes(cart):
    _, m = cart
    rng = np.random.default_rng(1)
    x = rng.uniform(-2, 2, (2, 3, 4))
    u = rng.uniform(-1, 1, (2, 3, 1))
    out = m.forward_dynamics(x, u)
    assert out.shape == (2, 3, 2)
    flat = m.forward_dynamics(x.reshape(-1, 4), u.reshape(-1, 1)).reshape(2, 3, 2)
    np.testing.assert_array_equal(out, flat)
    # one input: u may drop its last axis, or be one number for every state
    np.testing.assert_array_equal(m.forward_dynamics(x, u[..., 0]), out)
    const = m.forward_dynamics(x, 0.5)
    np.testing.assert_array_equal(const, m.forward_dynamics(x, np.full((2, 3, 1), 0.5)))
    # one state against many inputs broadcasts
    many = m.forward_dynamics(x[0, 0], u.reshape(-1, 1))
    assert many.shape == (6, 2)
    np.testing.assert_allclose(many[0], out[0, 0], rtol=1e-14)
    # the single-state (float) path equals the batched one
    for i in range(3):
        np.testing.assert_allclose(
            m.forward_dynamics(x[0, i], u[0, i]), out[0, i], rtol=1e-14, atol=1e-15
        )
    assert m.state_derivative(x, u).shape == (2, 3, 4)
    np.testing.assert_array_equal(m.state_derivative(x, u)[..., 2:], out)
    np.testing.assert_array_equal(m.state_derivative(x, u)[..., :2], x[..., 2:])
    q, qd = x[..., :2], x[..., 2:]
    assert m.mass_matrix(q, qd).shape == (2, 3, 2, 2)
    assert m.energy(q, qd).shape == (2, 3)
    assert m.inverse_dynamics(q, qd, out).shape == (2, 3, 2)
    assert m.energy(q[0, 0], qd[0, 0]).shape == ()


def test_inverse_dynamics_undoes_forward_dynamics(cart):
    _, m = cart
    rng = np.random.default_rng(2)
    x = rng.uniform(-2, 2, (50, 4))
    u = rng.uniform(-1, 1, (50, 1))
    qdd = m.forward_dynamics(x, u)
    tau = m.inverse_dynamics(x[:, :2], x[:, 2:], qdd)
    np.testing.assert_allclose(tau, u @ m.INPUT_MATRIX.T, atol=1e-13)
    passive = m.forward_dynamics(x)
    np.testing.assert_allclose(
        m.inverse_dynamics(x[:, :2], x[:, 2:], passive), 0.0, atol=1e-13
    )


def test_bad_shapes_raise(cart):
    _, m = cart
    with pytest.raises(ValueError, match=r"x must have shape \(\.\.\., 4\)"):
        m.forward_dynamics(np.zeros((3, 5)))
    with pytest.raises(ValueError, match="u must have shape"):
        m.forward_dynamics(np.zeros((3, 4)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="u must have 1 entries"):
        m.forward_dynamics(np.zeros(4), [1.0, 2.0])
    with pytest.raises(ValueError, match="q, q_dot and q_ddot"):
        m.mass_matrix(np.zeros(3), np.zeros(3))


def test_indefinite_rows_are_solved_with_pivoting():
    # M = [[x, 1], [1, 0]]: indefinite (det -1); its first pivot x vanishes at x = 0
    # and is tiny at x = 1e-13, where elimination without pivoting loses digits
    model = MechanicalModel(
        "0.5*x*x_dot**2 + x_dot*y_dot - 0.5*x**2 - 2*y**2", ["x", "y"]
    )
    m = load_python(export_source(model, "python"))
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, (20, 4))
    x[3, 0], x[5, 0] = 0.0, 1e-13
    u = rng.uniform(-1, 1, (20, 2))
    mass = m.mass_matrix(x[:, :2], x[:, 2:])
    rest = m.inverse_dynamics(x[:, :2], x[:, 2:], np.zeros((20, 2)))
    expected = np.linalg.solve(mass, (u - rest)[..., None])[..., 0]
    np.testing.assert_allclose(m.forward_dynamics(x, u), expected, rtol=1e-13)
    for i in (3, 5):
        np.testing.assert_allclose(
            m.forward_dynamics(x[i], u[i]), expected[i], rtol=1e-13
        )


def test_a_constant_zero_pivot_is_solved_with_pivoting():
    # M = [[0, 1], [1, 0]] everywhere: qdd_x = u_y - 4 y, qdd_y = u_x - x
    model = MechanicalModel("x_dot*y_dot - 0.5*x**2 - 2*y**2", ["x", "y"])
    m = load_python(export_source(model, "python"))
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, (20, 4))
    u = rng.uniform(-1, 1, (20, 2))
    expected = np.stack([u[:, 1] - 4 * x[:, 1], u[:, 0] - x[:, 0]], axis=1)
    np.testing.assert_allclose(m.forward_dynamics(x, u), expected, atol=1e-14)
    np.testing.assert_allclose(m.forward_dynamics(x[4], u[4]), expected[4], atol=1e-14)


def test_a_singular_mass_matrix_raises():
    model = MechanicalModel("0.5*x**2*x_dot**2 + 0.5*y_dot**2 - y**2", ["x", "y"])
    m = load_python(export_source(model, "python"))
    with pytest.raises(np.linalg.LinAlgError):
        m.forward_dynamics([0.0, 1.0, 0.2, 0.3])
    with pytest.raises(np.linalg.LinAlgError):
        m.forward_dynamics([[1.0, 1.0, 0.2, 0.3], [0.0, 1.0, 0.2, 0.3]])
    ok = m.forward_dynamics([[2.0, 1.0, 0.0, 0.3]])
    np.testing.assert_allclose(ok, [[0.0, -2.0]], atol=1e-15)


def test_the_header_records_the_provenance(cart):
    est, _ = cart
    text = export_source(est, "python", name="cartpole", date="2026-01-02")
    head = text[: text.index('"""', 3)]
    assert f"Generated by lagsindy {__version__} on 2026-01-02." in head
    assert "learned by LagrangianSINDy (case 'forces')" in head
    assert "Library: 4 candidate terms, 4 kept" in head
    assert "x_dot**2: 0.75" in head and "cos(theta): 4.905" in head
    assert f"viscous(theta): {VISCOUS!r}" in head
    assert f"coulomb(x): {COULOMB!r}" in head
    assert "State x = [x, theta, x_dot, theta_dot]" in head
    assert "Coulomb" not in head or "tanh" in head
    assert "-0.07*tanh(100.0*x_dot)" in head  # Q_x, with the smoothing velocity


def test_numbers_are_written_exactly():
    import sympy as sp

    c = 0.12345678901234568  # 17 significant digits
    theta, theta_dot = sp.symbols("theta theta_dot", real=True)
    # parsed from text, and as a learned model holds it (a Float of a Python float,
    # which sympy's own printers write with 15 digits)
    for lagrangian in (
        f"{c!r}*theta_dot**2 + 9.81*cos(theta)",
        sp.Float(c) * theta_dot**2 + sp.Float(9.81) * sp.cos(theta),
    ):
        model = MechanicalModel(lagrangian, ["theta"])
        for fmt in ("python", "c"):
            text = export_source(model, fmt)
            text = text if fmt == "python" else text[0]
            assert repr(2 * c) in text  # the mass, 2c, to the last bit
        m = load_python(export_source(model, "python"))
        assert m.mass_matrix([0.3], [0.0])[0, 0] == 2 * c


def test_a_saved_model_exports_the_same_code(cart, tmp_path):
    est, _ = cart
    path = save_model(est, tmp_path / "cart.json")
    loaded = load_model(path)
    for fmt in ("python", "c"):
        assert export_source(loaded, fmt, date="d") == export_source(est, fmt, date="d")
    # and the fitted state and the estimator export alike
    assert export_source(est.fitted_, "python", date="d") == export_source(
        est, "python", date="d"
    )


def test_export_model_writes_the_files(tmp_path):
    system = cart_pendulum()
    py = export_model(system, tmp_path / "cartpole.py")
    assert py.read_text().startswith('"""cartpole: equations of motion')
    c, h = export_model(system, tmp_path / "cartpole.c")
    assert (c.name, h.name) == ("cartpole.c", "cartpole.h")
    assert "int cartpole_forward_dynamics(" in h.read_text()
    c2, _ = export_model(system, tmp_path / "other", format="c")
    assert c2.name == "other.c"
    assert export_model(system, tmp_path / "plain").name == "plain.py"
    with pytest.raises(ValueError, match="format must be one of"):
        export_model(system, tmp_path / "x.py", format="fortran")


def test_unfitted_or_empty_models_are_refused(cart):
    from lagsindy import LagrangianSINDy

    with pytest.raises(ValueError, match="not fitted yet"):
        export_source(LagrangianSINDy(), "python")
    with pytest.raises(TypeError, match="expected a fitted LagrangianSINDy"):
        export_source(object(), "python")
    est, _ = cart
    with pytest.raises(ValueError, match=r"input_matrix must have shape \(n_dof=2"):
        export_source(est, "python", input_matrix=[[1.0, 0.0, 0.0]])
