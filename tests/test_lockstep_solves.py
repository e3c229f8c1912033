"""Batched (lockstep) FISTA and staged solves equal the one-problem solvers."""

import numpy as np
import pytest
import torch

from lagsindy.solvers import L1, GramQuadratic, fista, staged_fista
from lagsindy.solvers.fista import fista_batch
from lagsindy.solvers.staged import staged_fista_batch


def _gram(rng, n_rows, p, collinear=1e-3, n_true=3):
    A = rng.standard_normal((n_rows, p))
    A[:, 1] = A[:, 0] + collinear * A[:, 1]  # slow directions: long runs
    truth = rng.choice([-1.0, 1.0], n_true) * rng.uniform(0.3, 1.0, n_true)
    y = A[:, :n_true] @ truth + 0.01 * rng.standard_normal(n_rows)
    return A.T @ A / n_rows, A.T @ y / n_rows, float(y @ y / n_rows)


def _one(gram, rhs, const, lam, weights, mask, nonneg=None, step=None):
    """fista on the masked sub-problem, scattered back to full length."""
    idx = np.flatnonzero(mask)
    datafit = GramQuadratic(
        torch.tensor(gram[np.ix_(idx, idx)]), torch.tensor(rhs[idx]), const
    )
    pen = L1(
        lam,
        torch.tensor(weights[idx]),
        None if nonneg is None else torch.tensor(nonneg[idx]),
    )
    res = fista(datafit, pen, step=step, max_iter=3000, tol=1e-9)
    full = np.zeros(len(mask))
    full[idx] = res.coef.numpy()
    return full, res


@pytest.mark.parametrize("shared", [True, False])
def test_fista_batch_equals_fista_per_problem(shared):
    rng = np.random.default_rng(0)
    p, n_prob = 12, 7
    grams, rhss, consts = zip(*[_gram(rng, 300, p) for _ in range(n_prob)])
    if shared:  # one matrix, each problem a block of it (as case III's ranking)
        grams = [grams[0]] * n_prob
    mask = rng.random((n_prob, p)) < 0.8
    mask[:, 0] = True
    mask[0] = False  # a problem without coordinates
    weights = rng.uniform(0.5, 1.5, (n_prob, p))
    nonneg = rng.random((n_prob, p)) < 0.3
    rhs, const = np.array(rhss), np.array(consts)
    res = fista_batch(
        grams[0] if shared else np.array(grams),
        rhs,
        const,
        1e-3,
        weights,
        np.zeros((n_prob, p)),
        mask,
        nonneg,
        max_iter=3000,
        tol=1e-9,
    )
    assert res.n_iter[0] == 0 and res.converged[0]
    iters = []
    for r in range(1, n_prob):
        want, one = _one(
            grams[r], rhs[r], const[r], 1e-3, weights[r], mask[r], nonneg[r]
        )
        np.testing.assert_allclose(res.coef[r], want, rtol=0, atol=1e-10)
        assert np.all(res.coef[r][~mask[r]] == 0)
        assert res.converged[r] == one.converged
        assert abs(int(res.n_iter[r]) - one.n_iter) <= 10  # one check period
        np.testing.assert_allclose(res.step[r], one.step, rtol=1e-12)
        iters.append(one.n_iter)
    # the problems stop at different iterations: the lockstep and the hand-over of
    # the last running problem are exercised
    assert len(set(iters)) > 2


def test_fista_batch_halves_a_step_above_two_over_l():
    rng = np.random.default_rng(1)
    gram, rhs, const = _gram(rng, 200, 6)
    mask = np.ones((2, 6), bool)
    weights = np.ones((2, 6))
    lip = np.linalg.eigvalsh(gram)[-1]
    steps = np.array([0.5 / lip, 9.0 / lip])
    res = fista_batch(
        gram,
        np.stack([rhs, rhs]),
        np.array([const, const]),
        1e-3,
        weights,
        np.zeros((2, 6)),
        mask,
        step=steps,
        max_iter=3000,
        tol=1e-9,
    )
    for r in range(2):
        want, one = _one(gram, rhs, const, 1e-3, weights[r], mask[r], step=steps[r])
        assert res.step_reductions[r] == one.step_reductions
        np.testing.assert_allclose(res.coef[r], want, atol=1e-10)
    assert res.step_reductions[1] > 0 == res.step_reductions[0]


def test_staged_fista_batch_equals_staged_fista():
    rng = np.random.default_rng(2)
    p = 10
    datafits, weights, thresholds = [], [], []
    for n_true in range(1, 6):
        g, b, c = _gram(rng, 400, p, n_true=n_true)
        datafits.append(GramQuadratic(torch.tensor(g), torch.tensor(b), c))
        weights.append(torch.ones(p, dtype=torch.float64))
        thresholds.append(torch.full((p,), 0.1, dtype=torch.float64))
    weights[1][0] = 0.0  # an unpenalised feature
    nonneg = [None, torch.arange(p) % 2 == 0, None, None, None]
    settings = dict(lam=1e-2, reference=0.0, tol=1e-6, solver_tol=1e-9)
    got = staged_fista_batch(
        datafits,
        penalty_weights=weights,
        threshold=thresholds,
        nonneg=nonneg,
        **settings,
    )
    for d, w, t, nn, res in zip(datafits, weights, thresholds, nonneg, got):
        want = staged_fista(d, penalty_weights=w, threshold=t, nonneg=nn, **settings)
        np.testing.assert_array_equal(res.support, want.support)
        np.testing.assert_allclose(res.coef.numpy(), want.coef.numpy(), atol=1e-12)
        assert res.cost == pytest.approx(want.cost, rel=1e-10, abs=1e-15)
        assert len(res.stages) == len(want.stages)
        for a, b in zip(res.stages, want.stages):
            np.testing.assert_array_equal(a.support, b.support)
            np.testing.assert_allclose(a.coef, b.coef, atol=1e-8)
    assert len({len(r.support) for r in got}) > 1


def test_solve_many_equals_solve(case_iii_problem):
    """The ranking's and the shortlist's batched solves equal one solve each."""
    p = case_iii_problem
    free = np.flatnonzero(p.identifiable)
    jobs = [(np.array([k for k in free if k != r]), r, -1.0, True, None) for r in free]
    ranked = p.solver.solve_many(p.balanced, jobs, p.penalty, 1.0, starts=1)
    again = [(f, r, s, c, res) for (f, r, s, c, _), (_, res) in zip(jobs, ranked)]
    full = p.solver.solve_many(p.balanced, again, p.penalty, 1.0)
    restarted = 0
    for i, ((f, r, s, c, _), (coef1, res1), (coef, res)) in enumerate(
        zip(jobs, ranked, full)
    ):
        if res is res1 and i % 3:  # one-by-one solves of a third of the one-start
            continue  # candidates and of every restarted one (suite time)
        args = (p.balanced, f, r, s, p.penalty, 1.0, 0)
        want1, one1 = p.solver.solve(*args, starts=1)
        want, one = p.solver.solve(*args)
        for got_c, got_r, want_c, want_r in (
            (coef1, res1, want1, one1),
            (coef, res, want, one),
        ):
            np.testing.assert_array_equal(got_c != 0, want_c != 0)
            # The batch refits in NumPy, one solve in torch: on ill-conditioned
            # supports they differ by up to 8.8e-11 relative on the development
            # host and 1.1e-10 with torch's generic (non-SIMD) kernels.
            np.testing.assert_allclose(got_c, want_c, rtol=1e-9, atol=1e-14)
            assert got_r.cost == pytest.approx(want_r.cost, rel=1e-10, abs=1e-15)
            for a, b in zip(got_r.stages, want_r.stages, strict=True):
                np.testing.assert_array_equal(a.support, b.support)
        restarted += res is not res1
    assert restarted > 0  # some candidates need the second start on these data


def test_solve_many_batches_several_cpu_problems(monkeypatch, case_iii_problem):
    """Several double-precision CPU problems go through the lockstep solver (one
    call per start), a single one through solve."""
    from lagsindy.cases import sparse

    p = case_iii_problem
    calls = []

    def counted(datafits, **kwargs):
        calls.append(len(datafits))
        return staged_fista_batch(datafits, **kwargs)

    monkeypatch.setattr(sparse, "staged_fista_batch", counted)
    free = np.flatnonzero(p.identifiable)
    jobs = [(free[free != r], r, -1.0, True, None) for r in free[:3]]
    p.solver.solve_many(p.balanced, jobs, p.penalty, 1.0, starts=1)
    assert calls == [3]
    calls.clear()
    p.solver.solve_many(p.balanced, jobs[:1], p.penalty, 1.0, starts=1)
    assert calls == []


def test_staged_fista_batch_keeps_a_small_unpenalised_feature():
    """The hard threshold spares unpenalised (known) features, as staged_fista."""
    rng = np.random.default_rng(5)
    p, n = 8, 400
    A = rng.standard_normal((n, p))
    y = A[:, :3] @ np.array([0.01, 1.0, -0.8]) + 0.001 * rng.standard_normal(n)
    datafits = [
        GramQuadratic(torch.tensor(A.T @ A / n), torch.tensor(A.T @ y / n), y @ y / n)
    ] * 2
    weights = [torch.ones(p, dtype=torch.float64) for _ in range(2)]
    weights[0][0] = 0.0  # feature 0 known in the first problem only
    thresholds = [torch.full((p,), 0.1, dtype=torch.float64)] * 2
    settings = dict(lam=1e-3, reference=0.0, tol=1e-6, solver_tol=1e-9)
    got = staged_fista_batch(
        datafits, penalty_weights=weights, threshold=thresholds, **settings
    )
    for d, w, t, res in zip(datafits, weights, thresholds, got):
        want = staged_fista(d, penalty_weights=w, threshold=t, **settings)
        np.testing.assert_array_equal(res.support, want.support)
        np.testing.assert_allclose(res.coef.numpy(), want.coef.numpy(), atol=1e-12)
    # 0.01 is below a tenth of the largest: kept only where it is not penalised
    assert 0 in got[0].support and 0 not in got[1].support


def test_a_residual_at_the_floor_needs_no_bound(monkeypatch):
    """A first start whose residual is at PATH_FLOOR stops without the dense
    bound (the bound is >= 0, so it could not restart the path): only the other
    problems' bounds are computed, in the batch and in one solve."""
    from conftest import first_problem

    from lagsindy import LagrangianSINDy
    from lagsindy.cases import sparse
    from lagsindy.systems import cart_pendulum, make_dataset

    system = cart_pendulum()
    data = make_dataset(system, n_trajectories=10, excitation=None, random_state=0)
    p = first_problem(
        LagrangianSINDy(system.paper_library()), data.X, groups=data.groups
    )
    free = np.flatnonzero(p.identifiable)
    jobs = [(free[free != r], r, -1.0, True, None) for r in free]
    ranked = p.solver.solve_many(p.balanced, jobs, p.penalty, 1.0, starts=1)
    costs = np.array([res.cost for _, res in ranked])
    at_floor = costs <= sparse.PATH_FLOOR
    assert at_floor.any() and not at_floor.all()  # measured: 4 of 38 at <= 1.4e-10
    seen = []

    def counted(datafits):
        seen.extend(d.const for d in datafits)
        return dense_residuals(datafits)

    dense_residuals = sparse.dense_residuals
    monkeypatch.setattr(sparse, "dense_residuals", counted)
    again = [(f, r, s, c, res) for (f, r, s, c, _), (_, res) in zip(jobs, ranked)]
    p.solver.solve_many(p.balanced, again, p.penalty, 1.0)
    assert len(seen) == int((~at_floor).sum())

    def never(datafit):
        raise AssertionError("the bound of a path at the floor was computed")

    monkeypatch.setattr(sparse, "dense_residual", never)
    f, r, s, c, first = again[int(np.flatnonzero(at_floor)[0])]
    coef, res = p.solver.solve(p.balanced, f, r, s, p.penalty, 1.0, 0, first=first)
    assert res is first


def test_mass_problem_batched_with_the_ranking_equals_its_own_solve(
    monkeypatch, case_iii_problem
):
    """solve_many's extra problems (the mass normalization's first problem, solved
    in the ranking's batch) give the outcome of their own staged solve, and the
    search uses that result for the mass normalization's first start."""
    from lagsindy.cases import fixed, sparse

    p = case_iii_problem
    free, pivot, t_scaled = fixed._mass_start(p)
    datafit, features, weights, _ = fixed._pivot_problem(p, free, pivot, t_scaled)
    jobs = [(free[free != r], r, -1.0, True, None) for r in free[:4]]
    calls = []

    def counted(datafits, **kwargs):
        calls.append((len(datafits), kwargs["shared"] is None))
        return staged_fista_batch(datafits, **kwargs)

    monkeypatch.setattr(sparse, "staged_fista_batch", counted)
    extra = [(datafit, features, weights)]
    for starts in (1, None):
        calls.clear()
        out = p.solver.solve_many(p.balanced, jobs, p.penalty, 1.0, starts, extra)
        assert len(out) == len(jobs) + 1
        assert calls[0] == (5, True)  # one batch, on each problem's own matrix
        want = p.solver.stages(
            datafit, features, weights, 0, reference=1.0, starts=starts
        )
        got = out[-1]
        np.testing.assert_array_equal(got.support, want.support)
        # measured: 2.2e-16 relative
        np.testing.assert_allclose(got.coef.numpy(), want.coef.numpy(), rtol=1e-10)
        assert got.cost == pytest.approx(want.cost, rel=1e-10)
        for (coef, res), (f, r, s, c, _) in zip(out, jobs):
            want_c, _ = p.solver.solve(p.balanced, f, r, s, p.penalty, 1.0, 0, starts)
            np.testing.assert_allclose(coef, want_c, rtol=1e-9, atol=1e-14)
    # A problem of another size is solved on its own, after the batch.
    calls.clear()
    small = [
        (free[(free != r) & (free != free[-1])], r, -1.0, True, None) for r in free[:2]
    ]
    out = p.solver.solve_many(p.balanced, small, p.penalty, 1.0, 1, extra)
    assert calls == [(2, False)] and len(out) == 3
    # ... with the starts asked for (one here: the ranking's first start)
    one = p.solver.stages(datafit, features, weights, 0, 1, reference=1.0)
    np.testing.assert_array_equal(out[-1].support, one.support)
    assert out[-1].cost == pytest.approx(one.cost, rel=1e-12)
    assert len(out[-1].stages) == len(one.stages)

    # The search hands the batched one-start result to the mass solve.
    firsts = []
    solve_mass = fixed.solve_mass
    monkeypatch.setattr(
        fixed, "solve_mass", lambda *a: firsts.append(a[2:]) or solve_mass(*a)
    )
    fixed.fit_fixed(p)
    assert len(firsts) == 1 and firsts[0][0] is not None
    assert firsts[0][0].stages  # a staged result, in the problem's variables

    # Given that result, the mass solve runs only the later starts.
    lams = []
    staged = sparse.SparseSolve.staged
    monkeypatch.setattr(
        sparse.SparseSolve,
        "staged",
        lambda self, d, lam, *a, **k: lams.append(lam) or staged(self, d, lam, *a, **k),
    )
    first = p.solver.solve_many(p.balanced, jobs, p.penalty, 1.0, 1, extra)[-1]
    coef, _, _ = solve_mass(p, 0, first)
    assert p.solver.lam not in lams
    lams.clear()
    np.testing.assert_allclose(solve_mass(p, 0)[0], coef, rtol=1e-10, atol=1e-14)
    assert p.solver.lam in lams
