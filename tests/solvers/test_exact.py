"""FISTA's exact finishes (lagsindy.solvers.exact): the minimiser of a steady
support, the active-set search, and their use inside fista."""

import importlib

import numpy as np
import pytest
import torch
from lasso_problems import known_lasso, solve_stacked, wandering_lasso

from lagsindy.solvers import L1, GramQuadratic, fista, fista_batch, staged_fista
from lagsindy.solvers.exact import _active_set, _kkt_distance, _polish

# the module of the iterations
loop_module = importlib.import_module("lagsindy.solvers._loop")


def test_polish_returns_the_minimiser_of_the_right_pattern_only():
    G, b, lam, x = known_lasso()
    lw = np.full((1, x.size), lam)
    ones = np.ones((1, x.size))
    near = x * (1 + 0.1 * np.cos(np.arange(x.size)))  # same support and signs
    got, optimal, dist = _polish(G, b[None], lw, None, near[None], ones, 1e-10)
    assert optimal[0] and dist[0] < 1e-10
    np.testing.assert_allclose(got[0], x, rtol=0, atol=1e-10)  # measured 1e-14
    missing = near.copy()
    missing[4] = 0.0  # the support lacks a term: its KKT condition fails
    _, optimal, _ = _polish(G, b[None], lw, None, missing[None], ones, 1e-10)
    assert not optimal[0]
    flipped = near.copy()
    flipped[4] *= -1  # a wrong sign: the solve's sign disagrees
    _, optimal, _ = _polish(G, b[None], lw, None, flipped[None], ones, 1e-10)
    assert not optimal[0]


def _search(G, b, lw, nn, start, tol, max_steps=None):
    """The active-set search of one problem (1-d arrays), a batch of one."""
    x, ok, dist = _active_set(
        G, b[None], lw[None], None if nn is None else nn[None], start[None],
        np.ones((1, b.size)), tol, max_steps,
    )  # fmt: skip
    return x[0], bool(ok[0]), float(dist[0])


def _kkt(G, b, lam, w, nn=None):
    return float(_kkt_distance(w, G @ w - b, np.full(w.size, lam), nn).max())


def test_active_set_search_finds_the_known_minimiser_from_zero():
    G, b, lam, x = wandering_lasso()
    got, ok, dist = _search(G, b, np.full(x.size, lam), None, np.zeros_like(x), 1e-10)
    assert ok and dist <= 1e-10
    np.testing.assert_allclose(got, x, rtol=0, atol=1e-10)  # measured 2e-12


def test_active_set_search_drops_many_coordinates_at_once():
    """From a dense start whose full-set solve flips the signs off the support,
    the jump that zeroes every flipped coordinate saves steps."""
    G, b, lam, x = wandering_lasso()
    lw = np.full(x.size, lam)
    off = x == 0
    signs = np.where(off, 1.0, np.sign(x))
    for _ in range(5):  # off-support signs opposite to the full-set solve's
        signs[off] = -np.sign(np.linalg.solve(G, b - lw * signs)[off])
    start = np.where(off, 1e-3 * signs, x)
    got, ok, _ = _search(G, b, lw, None, start, 1e-10, max_steps=13)
    assert ok  # measured: 13 steps (16 with the one-coordinate steps alone)
    np.testing.assert_allclose(got, x, rtol=0, atol=1e-10)


def _steps_to_finish(G, b, lw, start, nn=None):
    for k in range(1, 100):
        x, ok, _ = _search(G, b, lw, nn, start, 1e-10, max_steps=k)
        if ok:
            return k, x
    raise AssertionError("the search did not finish")


def _clamp_problem(seed):
    """Nearly collinear pairs of columns and a dense start: G, b, weights, start."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((200, 30))
    a[:, 10:20] = a[:, :10] + 0.05 * rng.standard_normal((200, 10))
    G = a.T @ a / 200
    w = np.zeros(30)
    w[[0, 3, 7, 12, 25]] = [1.0, -2.0, 0.5, 1.5, -1.0]
    b = G @ w + 0.01 * rng.standard_normal(30)
    return G, b, np.full(30, 0.05), 0.3 * rng.standard_normal(30)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_clamped_points_let_several_coordinates_leave_in_one_step(monkeypatch, seed):
    """Nearly collinear pairs of columns and a dense start: with the points where
    every coordinate that passed zero is set to zero, fewer steps, same minimiser."""
    G, b, lw, start = _clamp_problem(seed)
    exact = importlib.import_module("lagsindy.solvers.exact")
    with_clamp, x = _steps_to_finish(G, b, lw, start)
    monkeypatch.setattr(exact, "CLAMP_POINTS", False)
    without, x_plain = _steps_to_finish(G, b, lw, start)
    # measured (seeds 0, 1, 2): 8, 10, 11 steps with them; 19, 15, 17 without
    assert with_clamp <= without - 4
    # measured 3e-17: both end on the same solve, and the last point chosen may
    # be the target or the segment's end (equal objectives, rounding decides)
    np.testing.assert_allclose(x, x_plain, rtol=0, atol=2e-15)
    assert _kkt(G, b, 0.05, x) <= 1e-10


def test_active_set_search_keeps_non_negative_coordinates():
    G, b, lam, x = wandering_lasso()
    nn = x > 0  # the positive coordinates of the minimiser, and no others
    start = np.where(nn, -0.5, 0.3)  # infeasible where non-negative: projected first
    got, ok, _ = _search(G, b, np.full(x.size, lam), nn, start, 1e-10)
    assert ok
    np.testing.assert_allclose(got, x, rtol=0, atol=1e-10)
    assert np.all(got[nn] >= 0)


def test_active_set_search_reports_failure_instead_of_a_wrong_answer():
    G, b, lam, x = wandering_lasso()
    got, ok, dist = _search(
        G, b, np.full(x.size, lam), None, np.zeros_like(x), 1e-10, max_steps=3
    )
    # three steps add at most three of the fifteen coordinates: not optimal, said so
    assert not ok and dist > 1e-10
    assert dist == pytest.approx(_kkt(G, b, lam, got))


def test_batched_search_gives_each_rows_own_search():
    """Rows of their own matrices, one with non-negative coordinates, one with a
    step budget that runs out: each row's outcome is that of its own search."""
    problems = [_clamp_problem(s) for s in (0, 1, 2)]
    G, b, lam, x = wandering_lasso()
    problems.append((G, b, np.full(30, lam), np.where(x > 0, -0.5, 0.3)))
    nn = np.zeros((4, 30), dtype=bool)
    nn[3] = x > 0
    gram = np.stack([p[0] for p in problems])
    rhs, lw, start = (np.stack([p[k] for p in problems]) for k in (1, 2, 3))
    got, ok, dist = _active_set(gram, rhs, lw, nn, start, np.ones_like(rhs), 1e-10)
    assert ok.all()
    for r, (G_r, b_r, lw_r, start_r) in enumerate(problems):
        want, ok_r, _ = _search(G_r, b_r, lw_r, nn[r] if r == 3 else None,
                                    start_r, 1e-10)  # fmt: skip
        assert ok_r
        assert np.array_equal(got[r] != 0, want != 0)
        np.testing.assert_allclose(got[r], want, rtol=0, atol=1e-14)  # measured 0
        assert dist[r] <= 1e-10
    assert np.all(got[3][nn[3]] >= 0)
    np.testing.assert_allclose(got[3], x, rtol=0, atol=1e-10)


def test_batched_search_where_non_negativity_binds():
    """Non-negative coordinates whose unconstrained minimiser is negative (and, in
    one row, unpenalised ones): each row's constrained minimiser, as one by one."""
    G, b, lam, x = wandering_lasso()
    nn, lw, start = [], [], []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        nn.append(rng.random(30) < 0.7)
        lw.append(np.full(30, lam))
        start.append(rng.uniform(-0.5, 1.0, 30))
    lw[1][[0, 5, 9]] = 0.0
    nn, lw, start = np.array(nn), np.array(lw), np.array(start)
    rhs = np.tile(b, (3, 1))
    got, ok, dist = _active_set(G, rhs, lw, nn, start, np.ones_like(rhs), 1e-10)
    assert ok.all()
    for r in range(3):
        want, ok_r, _ = _search(G, b, lw[r], nn[r], start[r], 1e-10)
        assert ok_r
        np.testing.assert_allclose(got[r], want, rtol=0, atol=1e-14)  # measured 0
        assert np.all(got[r][nn[r]] >= 0)
        # the constraint binds: 5, 4 and 5 coordinates held at zero
        assert np.sum((got[r] == 0) & nn[r] & (x < 0)) >= 4
        kkt = _kkt_distance(got[r], G @ got[r] - b, lw[r], nn[r]).max()
        assert kkt <= 1e-10 and dist[r] == pytest.approx(kkt)  # measured 7e-16
    # and in as many steps (the non-negative coordinates stop the segments)
    needed = [_steps_to_finish(G, b, lw[r], start[r], nn[r])[0] for r in range(3)]
    assert needed == [20, 20, 19]  # measured
    for k in range(min(needed) - 1, max(needed) + 1):
        _, ok, _ = _active_set(G, rhs, lw, nn, start, np.ones_like(rhs), 1e-10, k)
        assert ok.tolist() == [n <= k for n in needed]


@pytest.mark.parametrize("clamp", [True, False])
def test_batched_search_takes_the_steps_of_the_one_row_search(monkeypatch, clamp):
    """In lockstep, each row finishes in as many steps as its search alone (with
    and without the clamped points): one step fewer leaves it unfinished."""
    exact = importlib.import_module("lagsindy.solvers.exact")
    monkeypatch.setattr(exact, "CLAMP_POINTS", clamp)
    problems = [_clamp_problem(s) for s in (0, 1, 2)]
    gram = np.stack([p[0] for p in problems])
    rhs, lw, start = (np.stack([p[k] for p in problems]) for k in (1, 2, 3))
    needed = [_steps_to_finish(*p)[0] for p in problems]
    # measured: 8, 10, 11 with the clamped points; 19, 15, 17 without
    assert needed == ([8, 10, 11] if clamp else [19, 15, 17])
    ones = np.ones_like(rhs)
    for k in sorted(set(needed)):
        _, ok, _ = _active_set(gram, rhs, lw, None, start, ones, 1e-10, k)
        assert ok.tolist() == [n <= k for n in needed]
        _, ok, _ = _active_set(gram, rhs, lw, None, start, ones, 1e-10, k - 1)
        assert ok.tolist() == [n <= k - 1 for n in needed]


def test_batched_search_on_blocks_of_one_matrix_with_a_failing_row():
    """A shared matrix and each row's coordinates (fmask): the rows' minimisers on
    their blocks; a row that runs out of steps or meets a singular block says so
    and does not stop the others."""
    G, b, lam, x = wandering_lasso()
    rng = np.random.default_rng(3)
    masks = np.ones((4, 30))
    masks[1, rng.choice(30, 6, replace=False)] = 0
    masks[2, ::3] = 0
    # Coordinate 4 without a column (zero row and column) and non-zero at the
    # start: its block is singular with an exactly zero pivot on any LAPACK. (A
    # repeated column left a pivot of 1e-17 or exactly 0 depending on the BLAS
    # kernels, and where it was 1e-17 the searches converged.)
    singular = G.copy()
    singular[4], singular[:, 4] = 0.0, 0.0
    gram = np.stack([G, G, G, singular])
    rhs = b * masks
    lw = lam * masks
    start = 0.3 * np.cos(np.arange(30)) * masks
    got, ok, dist = _active_set(gram, rhs, lw, None, start, masks, 1e-10)
    for r in range(3):
        on = masks[r] > 0
        want, ok_r, _ = _search(G[np.ix_(on, on)], b[on], lw[r, on], None,
                                    start[r, on], 1e-10)  # fmt: skip
        assert ok[r] and ok_r
        np.testing.assert_allclose(got[r, on], want, rtol=0, atol=1e-13)  # measured 0
        assert np.all(got[r, ~on] == 0)
    np.testing.assert_allclose(got[0], x, rtol=0, atol=1e-10)
    want, ok_3, dist_3 = _search(singular, b, lw[3], None, start[3], 1e-10)
    assert start[3, 4] != 0
    assert not ok[3] and not ok_3  # the zero column makes the full block singular
    assert dist[3] == pytest.approx(dist_3)
    # the same shared matrix without a batch dimension
    shared, ok_s, _ = _active_set(G, rhs[:3], lw[:3], None, start[:3],
                                        masks[:3], 1e-10)  # fmt: skip
    assert ok_s.all()
    np.testing.assert_allclose(shared, got[:3], rtol=0, atol=1e-13)


def test_fista_batch_runs_the_search_on_many_problems():
    """Fourteen problems (more than the search once ran on, one at a time) all end
    by the batched search at the first try."""
    problems = [wandering_lasso(seed=s) for s in range(1, 15)]
    res = solve_stacked(problems)
    assert res.converged.all()
    for r, (_, _, _, x) in enumerate(problems):
        np.testing.assert_allclose(res.coef[r], x, rtol=0, atol=1e-10)
    assert res.n_iter.max() == 50  # measured: 50 each


def test_fista_ends_by_the_active_set_search_where_it_wanders():
    G, b, lam, x = wandering_lasso()
    datafit = GramQuadratic(torch.tensor(G), torch.tensor(b), 0.0)
    res = fista(datafit, L1(lam), tol=1e-8, max_iter=20_000)
    assert res.converged
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=1e-10)
    # measured: 50 iterations (the first search); FISTA and the steady-support
    # finish alone took 940
    assert res.n_iter == 50


def test_fista_without_the_search_wanders(monkeypatch):
    """The previous test's problem is one where the search matters."""
    G, b, lam, x = wandering_lasso()
    monkeypatch.setattr(loop_module, "ACTIVE_SET_AT", frozenset())
    datafit = GramQuadratic(torch.tensor(G), torch.tensor(b), 0.0)
    res = fista(datafit, L1(lam), tol=1e-8, max_iter=20_000)
    assert res.n_iter > 500  # measured 940
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=1e-10)


def test_fista_batch_ends_its_last_problems_by_the_search():
    problems = [wandering_lasso(seed=s) for s in (1, 2, 3)]
    res = solve_stacked(problems)
    assert res.converged.all()
    for r, (_, _, _, x) in enumerate(problems):
        np.testing.assert_allclose(res.coef[r], x, rtol=0, atol=1e-10)
    # measured: 50 each (without the search 940, 1110 and 830 one by one)
    assert res.n_iter.max() == 50


def test_a_warm_start_on_the_minimisers_support_needs_no_iteration():
    G, b, lam, x = wandering_lasso()
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
    G, b, lam, x = wandering_lasso()
    datafit = GramQuadratic(torch.tensor(G), torch.tensor(b), float(b @ b))
    res = staged_fista(datafit, lam=lam, threshold=1e-6, tol=0.0, max_stages=3)
    assert [st.n_iter for st in res.stages][1:] == [0, 0]
