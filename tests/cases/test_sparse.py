"""The staged sparse solve with an estimator's settings (lagsindy.cases.sparse):
settings, the multi-start path, and one problem, problems cut from one matrix and
one job on several matrices all getting the path of their own solve."""

import dataclasses

import numpy as np
import pytest
import torch

from lagsindy import CandidateLibrary, LagrangianSINDy, pipeline
from lagsindy.cases import SparseSolve, sparse
from lagsindy.formulation.scaling import BalancedGram
from lagsindy.solvers import StagedFISTA, staged_fista_batch
from lagsindy.solvers import staged as staged_module


def _solver(n_features, lam=1e-3, **settings):
    return SparseSolve.from_settings(
        StagedFISTA(**settings),
        lam=lam,
        alpha=None,
        n_terms=n_features,
        dissipative=np.zeros(n_features, dtype=bool),
    )


def _balanced(A, n_features):
    """BalancedGram of the columns of ``A`` (one coordinate)."""
    return BalancedGram(torch.tensor(A.T @ A)[None], A.shape[0], n_features)


def _resamples(count=12, seed=1):
    """Bootstrap-like resamples of a case I regression with a small term (0.05)
    and two nearly collinear columns: some paths keep their first start, some take
    the second (lam / 10)."""
    rng = np.random.default_rng(seed)
    n = 400
    Z = rng.standard_normal((n, 6))
    Z[:, 3] = Z[:, 0] + 0.05 * rng.standard_normal(n)
    y = Z @ np.array([1.0, -0.8, 0.05, 0.0, 0.0, 0.0]) + 0.1 * rng.standard_normal(n)
    A = np.concatenate([Z, y[:, None]], 1)
    return [_balanced(A[rng.integers(0, n, n)], 6) for _ in range(count)]


# ----------------------------------------------------------------- settings
def test_from_settings_and_the_estimators_setup():
    settings = StagedFISTA(threshold=0.2)
    solver = SparseSolve.from_settings(
        settings, lam=0.05, alpha=None, n_terms=3, dissipative=[0, 0, 0, 1], verbose=2
    )
    assert solver.settings is settings
    assert (solver.lam, solver.alpha, solver.verbose) == (0.05, None, 2)
    # the settings' parameters read through; replace keeps them
    assert solver.max_iter == solver.settings.max_iter == 20_000
    quiet = dataclasses.replace(solver, verbose=0)
    assert quiet.verbose == 0 and quiet.settings is solver.settings
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        solver.nothing  # noqa: B018
    np.testing.assert_array_equal(solver.thresholds([0, 2, 3]), [0.2, 0.2, 1e-3])
    assert solver.nonneg([0, 1], "cpu") is None
    assert solver.nonneg([1, 3], "cpu").tolist() == [False, True]
    # the settings are checked
    with pytest.raises(ValueError, match="max_stages"):
        SparseSolve.from_settings(StagedFISTA(max_stages=0), lam=0.1, alpha=None,
                                  n_terms=3, dissipative=[False] * 3)  # fmt: skip
    # an estimator's setup: its solver object, or the deprecated flat parameters
    library = CandidateLibrary.polynomial(["x"], degree=2).build()
    for est in (
        LagrangianSINDy(lam=0.05, solver=StagedFISTA(max_stages=2)),
        LagrangianSINDy(lam=0.05, max_stages=2),
    ):
        setup = pipeline.make_setup(est.get_params(), library, pipeline.Dissipation(),
                                    "forces")  # fmt: skip
        assert setup.solver.max_stages == 2 and setup.solver.lam == 0.05
        expected = StagedFISTA(max_stages=2).get_params()
        assert setup.solver.settings.get_params() == expected


@pytest.mark.parametrize(
    "ratio, second",
    [(1 + sparse.PATH_TIE - 1e-6, True), (1 + sparse.PATH_TIE + 1e-6, False)],
)
def test_the_sparsest_path_within_the_tie_wins(ratio, second):
    """Of the starts' results, the sparsest whose residual is within PATH_TIE of
    the best (just inside: the sparser second start; just outside: the first)."""

    def result(cost, n_terms):
        coef = torch.zeros(5)
        coef[:n_terms] = 1.0
        return staged_module.StagedResult(coef, None, [], 0, True, cost)

    first, sparser = result(1.0, 4), result(ratio, 2)
    assert sparse._sparsest_near_best([first, sparser]) is (
        sparser if second else first
    )
    # equally sparse: the earlier start
    tied = result(1.0, 4)
    assert sparse._sparsest_near_best([first, tied]) is first


# ------------------------------------------------------------- the one path
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


def test_each_start_is_one_batched_call(monkeypatch, case_iii_problem):
    """solve_many's problems share one matrix and advance in lockstep: one
    staged_fista_batch call per start; a single problem is solved alone."""
    p = case_iii_problem
    calls, kinds = [], []

    def counted(datafits, **kwargs):
        calls.append((len(datafits), kwargs["shared"] is not None))
        return staged_fista_batch(datafits, **kwargs)

    batches = staged_module._batches

    def spied(datafits, shared):
        out = batches(datafits, shared)
        kinds.extend((len(m), kind.__name__, s is not None) for m, kind, s in out)
        return out

    monkeypatch.setattr(sparse, "staged_fista_batch", counted)
    monkeypatch.setattr(staged_module, "_batches", spied)
    free = np.flatnonzero(p.identifiable)
    jobs = [(free[free != r], r, -1.0, True, None) for r in free[:3]]
    p.solver.solve_many(p.balanced, jobs, p.penalty, 1.0, starts=1)
    assert calls == [(3, True)] and kinds == [(3, "Lockstep", True)]
    calls.clear(), kinds.clear()
    p.solver.solve_many(p.balanced, jobs[:1], p.penalty, 1.0, starts=1)
    assert calls == [(1, True)] and kinds == [(1, "Alone", False)]


def test_a_residual_at_the_floor_needs_no_bound(monkeypatch):
    """A first start whose residual is at PATH_FLOOR stops without the dense
    bound (the bound is >= 0, so it could not restart the path): only the other
    problems' bounds are computed, in a batch and in one solve. Column 2 is
    exactly x0 + 2 x1, so fitting any of the three by the others is exact."""
    rng = np.random.default_rng(0)
    x0, x1, x3, x4 = rng.standard_normal((4, 300))
    balanced = _balanced(np.stack([x0, x1, x0 + 2 * x1, x3, x4], 1), 5)
    solver = _solver(5)
    free = np.arange(5)
    jobs = [(free[free != r], r, -1.0, True, None) for r in free]
    ranked = solver.solve_many(balanced, jobs, np.ones(5), 1.0, starts=1)
    at_floor = np.array([res.cost for _, res in ranked]) <= sparse.PATH_FLOOR
    assert at_floor.tolist() == [True, True, True, False, False]  # measured 0, 0.99
    seen = []

    def counted(datafits):
        seen.extend(datafits)
        return dense_residuals(datafits)

    dense_residuals = sparse.dense_residuals
    monkeypatch.setattr(sparse, "dense_residuals", counted)
    starts = []
    monkeypatch.setattr(sparse, "staged_fista_batch",
                        lambda d, **kw: starts.append(len(d)) or staged_fista_batch(
                            d, **kw))  # fmt: skip
    again = [(f, r, s, c, res) for (f, r, s, c, _), (_, res) in zip(jobs, ranked)]
    solver.solve_many(balanced, again, np.ones(5), 1.0)
    assert len(seen) == 2
    # the two above the floor are at their bound (an independent column fitted by
    # the others, measured 0.99 both): no second start
    assert starts == []
    monkeypatch.setattr(sparse, "dense_residuals", lambda d: 1 / 0)
    f, r, s, c, first = again[0]
    coef, res = solver.solve(balanced, f, r, s, np.ones(5), 1.0, 0, first=first)
    assert res is first


def test_case_ii_datafits_take_one_start(monkeypatch):
    """A datafit that is not a Gram quadratic (case II's) runs one start: no dense
    bound exists for it."""
    from lagsindy.solvers import AccelerationDatafit

    g = torch.Generator().manual_seed(0)
    mass = torch.ones(50, 3, 1, 1, dtype=torch.float64)
    bias = torch.randn(50, 3, 1, dtype=torch.float64, generator=g)
    qdd = -bias[:, 0] - 0.5 * bias[:, 1]
    datafit = AccelerationDatafit(mass, bias, qdd, torch.ones(3, dtype=torch.float64))
    lams = []
    monkeypatch.setattr(sparse, "staged_fista_batch",
                        lambda d, **kw: lams.append(kw["lam"]) or staged_fista_batch(
                            d, **kw))  # fmt: skip
    solver = _solver(3, lam=1.0)  # far too strong: a Gram quadratic would restart
    w0 = torch.tensor([0.8, 0.4, 0.1], dtype=torch.float64)
    solver.stages(datafit, np.arange(3), torch.ones(3, dtype=torch.float64), 0,
                  w0=w0 / w0.norm())  # fmt: skip
    assert lams == [1.0]


def test_solve_across_equals_solve():
    """One job on several resampled matrices, batched: each gets its own solve's
    path (both starts where needed), up to rounding."""
    balanced = _resamples()
    solver = _solver(6, lam=0.1)
    penalty = np.ones(6)
    start = np.array([1.0, -0.8, 0.0, 0.0, 0.0, 0.0])
    got = solver.solve_across(balanced, np.arange(6), 6, 1.0, penalty, 0.0, start)
    lams = []
    for bal, (coef, res) in zip(balanced, got):
        want, one = solver.solve(bal, np.arange(6), 6, 1.0, penalty, 0.0, 0,
                                 start=start)  # fmt: skip
        np.testing.assert_array_equal(coef != 0, want != 0)
        # measured 3.9e-13 relative here (the batched refit, on nearly collinear
        # columns); on an Intel Xeon with numpy 2.5 and torch 2.11 a small
        # coefficient (0.059) differed by 2.9e-13 absolute, 4.9e-12 of itself but
        # 3.1e-13 of the largest: round-off of collinear columns is shared, so the
        # tolerance is relative to the largest coefficient
        scale = np.abs(want).max()
        np.testing.assert_allclose(coef, want, rtol=2e-12, atol=2e-12 * scale)
        assert [st.lam for st in res.stages] == [st.lam for st in one.stages]
        lams.append(res.stages[0].lam)
    # measured: eleven of twelve keep the first start, one takes the second
    assert 0.1 in lams and pytest.approx(0.01) in lams


def test_solve_across_leaves_unusable_matrices_alone(monkeypatch):
    """Statistics that are not finite, a zero target or a zero column of ``free``:
    None (to be solved alone), the others solved; a batch whose divergence guard
    gives up: None for all."""
    balanced = _resamples(count=5)
    good = _resamples(count=1)[0]
    bad_gram = good.gram.clone()
    bad_gram[0, 0] = np.nan
    nan = BalancedGram(bad_gram[None], 400, 6, normalize=False)
    zero_target, zero_column = (BalancedGram(good.gram.clone()[None], 400, 6)
                                for _ in range(2))  # fmt: skip
    zero_target.gram[6, :] = zero_target.gram[:, 6] = 0.0
    zero_column.col_scale[4] = 0.0
    mixed = [balanced[0], nan, zero_target, balanced[1], zero_column]
    solver = _solver(6, lam=0.1)
    got = solver.solve_across(mixed, np.arange(6), 6, 1.0, np.ones(6), 0.0)
    assert [g is None for g in got] == [False, True, True, False, True]

    def diverges(*args, **kwargs):
        raise FloatingPointError("FISTA diverged")

    monkeypatch.setattr(sparse, "staged_fista_batch", diverges)
    assert (
        solver.solve_across(balanced, np.arange(6), 6, 1.0, np.ones(6), 0.0)
        == [None] * 5
    )


def test_mass_problem_batched_with_the_ranking_equals_its_own_solve(
    monkeypatch, case_iii_problem
):
    """solve_many's extra problems (the mass normalization's first problem, solved
    in the ranking's batch) give the outcome of their own staged solve, and the
    search uses that result for the mass normalization's first start."""
    from lagsindy.cases import fixed

    p = case_iii_problem
    free, pivot, t_scaled = fixed._mass_start(p)
    datafit, features, weights, _ = fixed._pivot_problem(p, free, pivot, t_scaled)
    jobs = [(free[free != r], r, -1.0, True, None) for r in free[:4]]
    calls, lams = [], []

    def counted(datafits, **kwargs):
        calls.append((len(datafits), kwargs["shared"] is None))
        lams.append(kwargs["lam"])
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
    # A problem of another size goes in the same call, solved alone there.
    calls.clear()
    small = [
        (free[(free != r) & (free != free[-1])], r, -1.0, True, None) for r in free[:2]
    ]
    out = p.solver.solve_many(p.balanced, small, p.penalty, 1.0, 1, extra)
    assert calls == [(3, True)] and len(out) == 3
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
    first = p.solver.solve_many(p.balanced, jobs, p.penalty, 1.0, 1, extra)[-1]
    lams.clear()
    coef, _, _ = solve_mass(p, 0, first)
    assert p.solver.lam not in lams
    lams.clear()
    np.testing.assert_allclose(solve_mass(p, 0)[0], coef, rtol=1e-10, atol=1e-14)
    assert p.solver.lam in lams
