"""FISTA's exact finishes: the active-set search and the warm start's own support."""

import importlib

import numpy as np
import pytest
import torch

from lagsindy.solvers import L1, GramQuadratic, fista, staged_fista
from lagsindy.solvers.exact import _active_set
from lagsindy.solvers.fista import fista_batch

# the module (``lagsindy.solvers.fista`` is also the name of the function)
fista_module = importlib.import_module("lagsindy.solvers.fista")


def _wandering_lasso(seed=1, p=30, n_on=15, collinear=1e-2):
    """An L1 problem with a known minimiser on which FISTA wanders among supports.

    Fifteen pairs of nearly collinear columns (condition number ~1e5) and half the
    coordinates in the support: FISTA's iterates change support for hundreds of
    iterations. The minimiser ``x`` is built in: ``b`` puts the gradient at
    ``-lam sign(x)`` on the support and strictly inside ``(-lam, lam)`` off it.
    """
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((300, p))
    for j in range(0, p - 1, 2):
        A[:, j + 1] = A[:, j] + collinear * A[:, j + 1]
    G = A.T @ A / 300
    lam = 1e-3
    x = np.zeros(p)
    on = rng.choice(p, n_on, replace=False)
    x[on] = rng.choice([-1.0, 1.0], n_on) * rng.uniform(0.2, 1.0, n_on)
    b = G @ x + lam * np.sign(x)
    off = x == 0
    b[off] = (G @ x)[off] - lam * rng.uniform(-0.9, 0.9, off.sum())
    return G, b, lam, x


def _kkt(G, b, lam, w, nn=None):
    from lagsindy.solvers.exact import _kkt_distance

    return float(_kkt_distance(w, G @ w - b, np.full(w.size, lam), nn).max())


def test_active_set_search_finds_the_known_minimiser_from_zero():
    G, b, lam, x = _wandering_lasso()
    got, ok, dist = _active_set(
        G, b, np.full(x.size, lam), None, np.zeros_like(x), 1e-10
    )
    assert ok and dist <= 1e-10
    np.testing.assert_allclose(got, x, rtol=0, atol=1e-10)  # measured 2e-12


def test_active_set_search_drops_many_coordinates_at_once():
    """From a dense start whose full-set solve flips the signs off the support,
    the jump that zeroes every flipped coordinate saves steps."""
    G, b, lam, x = _wandering_lasso()
    lw = np.full(x.size, lam)
    off = x == 0
    signs = np.where(off, 1.0, np.sign(x))
    for _ in range(5):  # off-support signs opposite to the full-set solve's
        signs[off] = -np.sign(np.linalg.solve(G, b - lw * signs)[off])
    start = np.where(off, 1e-3 * signs, x)
    got, ok, _ = _active_set(G, b, lw, None, start, 1e-10, max_steps=13)
    assert ok  # measured: 13 steps (16 with the one-coordinate steps alone)
    np.testing.assert_allclose(got, x, rtol=0, atol=1e-10)


def test_active_set_search_keeps_non_negative_coordinates():
    G, b, lam, x = _wandering_lasso()
    nn = x > 0  # the positive coordinates of the minimiser, and no others
    start = np.where(nn, -0.5, 0.3)  # infeasible where non-negative: projected first
    got, ok, _ = _active_set(G, b, np.full(x.size, lam), nn, start, 1e-10)
    assert ok
    np.testing.assert_allclose(got, x, rtol=0, atol=1e-10)
    assert np.all(got[nn] >= 0)


def test_active_set_search_reports_failure_instead_of_a_wrong_answer():
    G, b, lam, x = _wandering_lasso()
    got, ok, dist = _active_set(
        G, b, np.full(x.size, lam), None, np.zeros_like(x), 1e-10, max_steps=3
    )
    # three steps add at most three of the fifteen coordinates: not optimal, said so
    assert not ok and dist > 1e-10
    assert dist == pytest.approx(_kkt(G, b, lam, got))


def test_fista_ends_by_the_active_set_search_where_it_wanders():
    G, b, lam, x = _wandering_lasso()
    datafit = GramQuadratic(torch.tensor(G), torch.tensor(b), 0.0)
    res = fista(datafit, L1(lam), tol=1e-8, max_iter=20_000)
    assert res.converged
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=1e-10)
    # measured: 50 iterations (the first search); FISTA and the steady-support
    # finish alone took 940
    assert res.n_iter == 50


def test_fista_without_the_search_wanders(monkeypatch):
    """The previous test's problem is one where the search matters."""
    G, b, lam, x = _wandering_lasso()
    monkeypatch.setattr(fista_module, "ACTIVE_SET_AT", frozenset())
    datafit = GramQuadratic(torch.tensor(G), torch.tensor(b), 0.0)
    res = fista(datafit, L1(lam), tol=1e-8, max_iter=20_000)
    assert res.n_iter > 500  # measured 940
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=1e-10)


def test_fista_batch_ends_its_last_problems_by_the_search():
    problems = [_wandering_lasso(seed=s) for s in (1, 2, 3)]
    G = np.stack([g for g, _, _, _ in problems])
    b = np.stack([b_ for _, b_, _, _ in problems])
    lam = problems[0][2]
    ones = np.ones_like(b)
    res = fista_batch(G, b, np.zeros(3), lam, ones, np.zeros_like(b), ones > 0)
    assert res.converged.all()
    for r, (_, _, _, x) in enumerate(problems):
        np.testing.assert_allclose(res.coef[r], x, rtol=0, atol=1e-10)
    # measured: 50 each (without the search 940, 1110 and 830 one by one)
    assert res.n_iter.max() == 50


def test_a_warm_start_on_the_minimisers_support_needs_no_iteration():
    G, b, lam, x = _wandering_lasso()
    datafit = GramQuadratic(torch.tensor(G), torch.tensor(b), 0.0)
    near = torch.tensor(x * (1 + 0.2 * np.cos(np.arange(x.size))))  # same signs
    res = fista(datafit, L1(lam), near, tol=1e-8)
    assert res.n_iter == 0 and res.converged
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=1e-10)
    # one coordinate off the support: the warm start is not optimal, FISTA runs
    wrong = near.clone()
    wrong[int(np.flatnonzero(x == 0)[0])] = 0.1
    res = fista(datafit, L1(lam), wrong, tol=1e-8)
    assert res.n_iter > 0 and res.converged
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=1e-10)
    # the same in a batch: the first row ends before iterating, the second does not
    w0 = np.stack([near.numpy(), wrong.numpy()])
    ones = np.ones_like(w0)
    out = fista_batch(G, np.stack([b, b]), np.zeros(2), lam, ones, w0, ones > 0)
    assert out.n_iter[0] == 0 and out.n_iter[1] > 0 and out.converged.all()
    np.testing.assert_allclose(out.coef, np.stack([x, x]), rtol=0, atol=1e-10)


def test_staged_stages_after_the_first_need_no_iteration_on_a_steady_support():
    G, b, lam, x = _wandering_lasso()
    datafit = GramQuadratic(torch.tensor(G), torch.tensor(b), float(b @ b))
    res = staged_fista(datafit, lam=lam, threshold=1e-6, tol=0.0, max_stages=3)
    assert [st.n_iter for st in res.stages][1:] == [0, 0]
