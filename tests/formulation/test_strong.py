"""The strong form: the operator's columns and their Gram statistics in chunks."""

import numpy as np
import pytest
import sympy as sp
import torch
from _sympy_reference import random_states, sympy_columns

import lagsindy.formulation.strong as strong_module
from lagsindy import CandidateLibrary
from lagsindy._expr import compile_torch, symbols_for
from lagsindy.evaluator import TorchTerms
from lagsindy.formulation.operator import (
    EulerLagrangeOperator,
    forward_accelerations,
)
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    single_pendulum,
    spherical_pendulum,
)

SYSTEMS = [single_pendulum, cart_pendulum, double_pendulum, spherical_pendulum]


def _random_states(n_dof, n, seed):
    return [t.numpy() for t in random_states(n_dof, n, seed)]


@pytest.mark.parametrize("system", SYSTEMS)
def test_true_lagrangian_has_zero_residual_on_exact_data(system):
    s = system()
    lib = s.paper_library()
    coef = s.true_coefficients(lib)
    q, qd, _ = _random_states(s.n_dof, 50, 2)
    if s.name == "spherical pendulum":  # away from sin(theta) = 0
        q[:, 0] = np.random.default_rng(3).uniform(0.5, 2.5, 50)
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


@pytest.mark.parametrize("cache", [1, 3000, 1 << 20])
def test_gram_in_reused_chunk_buffers_matches_sympy_columns(monkeypatch, cache):
    """The Gram accumulated chunk by chunk in one reused buffer (columns written in
    place, forces, extra columns and the target beside them) equals A^T A of the
    sympy columns, whatever the chunk size (1: the 256-row minimum; 3000 elements:
    chunks of 13 rows and a partial last chunk; the default: one chunk)."""
    monkeypatch.setattr(strong_module, "GRAM_CACHE", cache)
    monkeypatch.setattr(strong_module, "GRAM_MIN_CHUNK", 1 if cache > 1 else 256)
    names = ["x", "theta"]
    lib = CandidateLibrary.polynomial(names, angles=["theta"], degree=3).build()
    w1, w2 = sp.symbols("x_dot theta_dot", real=True)
    op = EulerLagrangeOperator(names, lib.terms_, forces=[[-w1, 0], [0, -(w2**3)]])
    q, qd, qdd = random_states(2, 300, 0)
    X = torch.cat([q, qd, qdd], dim=1)
    rng = np.random.default_rng(1)
    y = torch.tensor(rng.normal(size=(300, 2)))
    extra = torch.tensor(rng.normal(size=(300, 2, 1)))
    forces = -np.stack([-qd[:, 0].numpy(), -(qd[:, 1].numpy() ** 3)], 1)  # columns -Q
    force_cols = np.zeros((300, 2, 2))
    force_cols[:, 0, 0], force_cols[:, 1, 1] = forces[:, 0], forces[:, 1]
    a = np.concatenate(
        [
            sympy_columns(lib.terms_, names, q, qd, qdd),
            force_cols,
            extra.numpy(),
            y.numpy()[:, :, None],
        ],
        axis=2,
    )
    want = np.einsum("sip,siq->ipq", a, a)
    got = op.gram(X, y, extra=extra).numpy()
    # measured: 1.4e-16 of the largest entry, at every chunk size
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-13 * np.abs(want).max())


def test_gram_of_terms_split_between_batched_and_general_paths():
    """Batched and torch.func terms side by side, small chunks: the Gram equals
    A^T A of the columns, and the samples-last layouts hold the same values."""
    names = ["theta1", "theta2"]
    t1, t2 = sp.symbols(names, real=True)
    w1, w2 = sp.symbols(["theta1_dot", "theta2_dot"], real=True)
    terms = [w1 * w2 * sp.cos(t1 - t2), sp.exp(t1) * w1**2, (w1 + t2) ** 2]
    op = EulerLagrangeOperator(names, terms, forces=[[-w1, -w2]], chunk_size=7)
    q, qd, qdd = random_states(2, 25, 2)
    X = torch.cat([q, qd, qdd], dim=1)
    y = torch.tensor(np.random.default_rng(3).normal(size=(25, 2)))
    a = torch.cat([op.columns(X), y.unsqueeze(2)], dim=2).numpy()
    want = np.einsum("sip,siq->ipq", a, a)
    g = op.gram(X, y).numpy()
    np.testing.assert_allclose(g, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
    assert torch.equal(op.columns_t(X), op.columns(X).permute(1, 2, 0))
    assert torch.equal(
        op.mass_matrices_t(q, qd), op.mass_matrices(q, qd).permute(1, 2, 3, 0)
    )


def test_operator_of_a_torch_term_function_equals_the_sympy_one():
    """An operator built on a torch term function (no sympy terms) gives the
    columns, Gram statistics, mass matrices and parts of the same terms in sympy."""
    lib = double_pendulum().paper_library()
    names = lib.coordinates_
    terms = lib.terms_[::4]
    q_s, qd_s, _ = symbols_for(names)
    provider = TorchTerms([str(t) for t in terms], compile_torch(terms, (q_s, qd_s)))
    forces = [[-qd_s[0], qd_s[0] - qd_s[1]]]
    sym = EulerLagrangeOperator(names, terms, forces=forces)
    tor = EulerLagrangeOperator(names, provider, forces=forces)
    assert tor.n_terms == len(terms) and tor.n_columns == len(terms) + 1
    q, qd, qdd = random_states(2, 60, 8)
    X = torch.cat([q, qd, qdd], dim=1)
    y = torch.tensor(np.random.default_rng(9).normal(size=(60, 2)))
    for got, want in [
        (tor.columns(X), sym.columns(X)),
        (tor.gram(X, y), sym.gram(X, y)),
        (tor.mass_matrices(q, qd), sym.mass_matrices(q, qd)),
        *zip(tor.parts(q, qd), sym.parts(q, qd)),
    ]:
        got, want = got.numpy(), want.numpy()
        # measured: 3.5e-16 of the largest entry at most (rounding)
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-15 * np.abs(want).max())
