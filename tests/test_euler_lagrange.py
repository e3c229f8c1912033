import numpy as np
import pytest
import sympy as sp
import torch

from lagsindy._expr import symbols_for
from lagsindy.euler_lagrange import (
    EulerLagrangeOperator,
    forward_accelerations,
    lagrangian_columns,
    lagrangian_components,
)
from lagsindy.library import euler_lagrange_expressions
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    single_pendulum,
    spherical_pendulum,
)

SYSTEMS = [single_pendulum, cart_pendulum, double_pendulum, spherical_pendulum]


def _random_states(n_dof, n, seed):
    rng = np.random.default_rng(seed)
    return (
        rng.uniform(-np.pi, np.pi, (n, n_dof)),
        rng.uniform(-3, 3, (n, n_dof)),
        rng.uniform(-3, 3, (n, n_dof)),
    )


@pytest.mark.parametrize("system", SYSTEMS)
def test_columns_agree_with_sympy(system):
    """Autograd Theta equals sympy's Euler-Lagrange expressions to 1e-10."""
    lib = system().paper_library()
    names = lib.coordinates_
    q_s, qd_s, qdd_s = symbols_for(names)
    q, qd, qdd = _random_states(len(names), 25, 0)
    theta = lagrangian_columns(
        lib.to_torch(), torch.tensor(q), torch.tensor(qd), torch.tensor(qdd)
    ).numpy()
    args = q_s + qd_s + qdd_s
    for k, term in enumerate(lib.terms_):
        exprs = euler_lagrange_expressions(term, names)
        f = sp.lambdify(args, exprs, modules="numpy")
        want = np.stack(
            [np.broadcast_to(v, (25,)) for v in f(*q.T, *qd.T, *qdd.T)], axis=1
        )
        np.testing.assert_allclose(
            theta[:, :, k], want, rtol=1e-10, atol=1e-10, err_msg=str(term)
        )


def test_components_agree_with_sympy():
    lib = double_pendulum().paper_library()
    names = lib.coordinates_
    q_s, qd_s, _ = symbols_for(names)
    q, qd, _ = _random_states(2, 10, 1)
    m_mat, n_mat, o = (
        t.numpy()
        for t in lagrangian_components(
            lib.to_torch(), torch.tensor(q), torch.tensor(qd)
        )
    )
    args = q_s + qd_s
    for k in (0, 7, len(lib.terms_) - 1):
        term = lib.terms_[k]
        for i in range(2):
            f_o = sp.lambdify(args, sp.diff(term, q_s[i]))
            np.testing.assert_allclose(
                o[:, k, i], np.broadcast_to(f_o(*q.T, *qd.T), (10,)), atol=1e-10
            )
            for j in range(2):
                f_m = sp.lambdify(args, sp.diff(term, qd_s[i], qd_s[j]))
                f_n = sp.lambdify(args, sp.diff(term, qd_s[i], q_s[j]))
                np.testing.assert_allclose(
                    m_mat[:, k, i, j],
                    np.broadcast_to(f_m(*q.T, *qd.T), (10,)),
                    atol=1e-10,
                )
                np.testing.assert_allclose(
                    n_mat[:, k, i, j],
                    np.broadcast_to(f_n(*q.T, *qd.T), (10,)),
                    atol=1e-10,
                )


@pytest.mark.parametrize("system", SYSTEMS)
def test_true_lagrangian_has_zero_residual_on_exact_data(system):
    s = system()
    lib = s.paper_library()
    coef = s.true_coefficients(lib)
    q, qd, _ = _random_states(s.n_dof, 50, 2)
    if s.name == "spherical pendulum":
        q[:, 0] = np.random.default_rng(3).uniform(
            0.5, 2.5, 50
        )  # away from sin(theta) = 0
    qdd = s.forward_dynamics(q, qd)
    X = torch.tensor(np.concatenate([q, qd, qdd], axis=1))
    op = EulerLagrangeOperator(lib.coordinates_, lib.terms_)
    resid = (op.columns(X) @ torch.tensor(coef)).numpy()
    np.testing.assert_allclose(resid, 0.0, atol=1e-9)


def test_forward_accelerations_match_model():
    s = cart_pendulum()
    lib = s.paper_library()
    coef = s.true_coefficients(lib)
    keep = np.flatnonzero(coef)
    q, qd, _ = _random_states(2, 30, 4)
    tau = np.random.default_rng(5).normal(size=(30, 2))
    want = s.forward_dynamics(q, qd, tau)
    X = torch.tensor(np.concatenate([q, qd, np.zeros_like(q)], axis=1))
    op = EulerLagrangeOperator(lib.coordinates_, [lib.terms_[k] for k in keep])
    got = forward_accelerations(
        op, torch.tensor(coef[keep]), X, torch.tensor(tau)
    ).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)


def test_force_columns_and_gram_chunking():
    q_s, qd_s, _ = symbols_for(["x"])
    op = EulerLagrangeOperator(
        ["x"], [qd_s[0] ** 2, q_s[0] ** 2], forces=[[-qd_s[0]]], chunk_size=7
    )
    X = torch.tensor(np.random.default_rng(6).normal(size=(40, 3)))
    cols = op.columns(X).numpy()
    np.testing.assert_allclose(cols[:, 0, 0], 2 * X[:, 2].numpy())
    np.testing.assert_allclose(cols[:, 0, 1], -2 * X[:, 0].numpy())
    np.testing.assert_allclose(cols[:, 0, 2], X[:, 1].numpy())  # -Q = +x_dot
    y = torch.tensor(np.random.default_rng(7).normal(size=(40, 1)))
    g = op.gram(X, y).numpy()[0]
    a = np.concatenate([cols[:, 0, :], y.numpy()], axis=1)
    np.testing.assert_allclose(g, a.T @ a, rtol=1e-12, atol=1e-12 * np.abs(g).max())
