"""Case III search: the ranking solves only the candidates that can be shortlisted."""

import warnings

import numpy as np
import pytest

from lagsindy.cases import fixed
from lagsindy.formulation.scaling import fixed_term_bounds


def _brute_bounds(a):
    """Relative residual of each column's least-squares fit by all the others."""
    out = []
    for r in range(a.shape[1]):
        others = np.delete(a, r, axis=1)
        w, *_ = np.linalg.lstsq(others, -a[:, r], rcond=None)
        out.append(np.sum((others @ w + a[:, r]) ** 2) / np.sum(a[:, r] ** 2))
    return np.array(out)


def test_bounds_equal_least_squares():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((300, 8)) * [1.0, 3.0, 0.1, 1.0, 10.0, 1.0, 1.0, 2.0]
    a[:, 5] += 0.9 * a[:, 6]  # correlated columns: bounds well below 1
    got = fixed_term_bounds(a.T @ a)
    want = _brute_bounds(a)
    # measured: equal to 7e-13 (relative)
    np.testing.assert_allclose(got, want, rtol=1e-11)
    assert got.min() < 0.5 < got.max()


def test_bounds_of_a_null_combination_stay_at_rounding_level():
    rng = np.random.default_rng(1)
    a = rng.standard_normal((200, 6))
    a[:, 3] = a[:, 0] - 0.5 * a[:, 1]  # the columns 0, 1, 3 explain each other
    got = fixed_term_bounds(a.T @ a)
    want = _brute_bounds(a)
    # measured: <= 1.8e-12 where the least-squares residual is 0 (1e-30)
    assert np.all(got[[0, 1, 3]] < 1e-10)
    np.testing.assert_allclose(got[[2, 4, 5]], want[[2, 4, 5]], rtol=1e-11)
    assert np.all(got <= want + 1e-10)  # never above the true residual


def _solve_all(p, candidates, traces):
    free_all = np.flatnonzero(p.identifiable)
    jobs = [
        (free_all[free_all != r], r, -1.0, bool(traces[r] > 0), None)
        for r in candidates
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return p.solver.solve_many(p.balanced, jobs, p.penalty, 1.0, starts=1)


@pytest.fixture(scope="module")
def clean_search_problems():
    """Case III Problems of noise-free passive cart-pendulum searches, by the
    number of trajectories."""
    from conftest import first_problem

    from lagsindy import LagrangianSINDy
    from lagsindy.systems import cart_pendulum, make_dataset

    system = cart_pendulum()
    out = {}
    for n in (6, 20):
        data = make_dataset(system, n_trajectories=n, excitation=None, random_state=0)
        est = LagrangianSINDy(system.paper_library())
        out[n] = first_problem(est, data.X, groups=data.groups)
    return out


@pytest.mark.parametrize(
    "which, first",
    [(20, fixed.RANK_FIRST), (6, 1.0), ("noisy", fixed.RANK_FIRST)],
)
def test_ranking_keeps_the_shortlist_of_every_candidate(
    which, first, clean_search_problems, case_iii_problem, monkeypatch
):
    p = case_iii_problem if which == "noisy" else clean_search_problems[which]
    candidates = [k for k in np.flatnonzero(p.identifiable) if k < len(p.terms)]
    traces = np.zeros(p.n_features)
    monkeypatch.setattr(fixed, "RANK_FIRST", first)
    batches = []
    solve_many = p.solver.solve_many

    def spy(balanced, jobs, *args, **kwargs):
        batches.append(len(jobs))
        return solve_many(balanced, jobs, *args, **kwargs)

    monkeypatch.setattr(p.solver, "solve_many", spy)
    ranked, mass_first = fixed._rank(p, candidates, traces)
    assert mass_first is None  # no mass problem was given
    monkeypatch.undo()
    every = _solve_all(p, candidates, traces)
    costs = np.array([res.cost for _, res in every])
    order = np.argsort(costs, kind="stable")[: fixed.SELECTION_TOP]
    by_r = {r: (coef, res) for _, r, coef, res in ranked}
    got = sorted(by_r, key=lambda r: by_r[r][1].cost)[: fixed.SELECTION_TOP]
    assert got == [candidates[i] for i in order]
    for i in order:
        coef, res = by_r[candidates[i]]
        want = every[i][0].copy()
        want[candidates[i]] = 1.0
        # measured: equal bit for bit (the same refit of the same support); other
        # BLAS kernels may round the batches' padded products differently
        np.testing.assert_array_equal(coef != 0, want != 0)
        np.testing.assert_allclose(coef, want, rtol=1e-12, atol=0)
        # the batch's residual sums run over other coordinates: measured 5e-15
        np.testing.assert_allclose(res.cost, costs[i], rtol=1e-12)
    # Every candidate left out has a bound above the shortlist's last residual.
    g, _ = p.balanced.block(np.flatnonzero(p.identifiable))
    bound = dict(zip(np.flatnonzero(p.identifiable), fixed_term_bounds(g)))
    last = costs[order[-1]]
    for r in candidates:
        if r not in by_r:
            assert bound[r] > last
    assert sum(batches) == len(by_r)
    n = len(candidates)
    if which == 20:  # tight bounds: measured 13 of 39 solved, in one batch
        assert len(batches) == 1 and batches[0] <= 16
    elif which == 6:  # looser bounds, the first batch the 12 smallest: [12, 18]
        assert len(batches) == 2 and batches[0] == fixed.SELECTION_TOP
        assert sum(batches) < n
    else:  # a noise correction: most bounds 0, every candidate in one batch
        assert batches == [n]


def test_batched_dense_residuals_equal_one_at_a_time():
    """The shortlist's path bounds, batched by size, are dense_residual's values."""
    import torch

    from lagsindy.formulation.scaling import dense_residual, dense_residuals
    from lagsindy.solvers import GramQuadratic

    g = torch.Generator().manual_seed(0)
    problems = []
    for n in (5, 5, 7, 5, 0, 7):
        a = torch.randn(50, n, dtype=torch.float64, generator=g)
        if n == 7:
            a[:, 6] = a[:, 0] + a[:, 1]  # a null combination (dropped eigenvalue)
        y = torch.randn(50, dtype=torch.float64, generator=g)
        problems.append(GramQuadratic(a.T @ a, a.T @ y, float(y @ y)))
    want = [dense_residual(d) for d in problems]
    assert dense_residuals(problems) == want  # bit for bit (measured)
    assert len(set(want)) == len(want) and want[4] == 0.0


def test_problems_cut_from_one_block_equal_problem_bit_for_bit():
    import torch

    from lagsindy.formulation.scaling import BalancedGram

    rng = np.random.default_rng(4)
    a = rng.standard_normal((2, 200, 9)) * rng.uniform(0.1, 10.0, 9)
    a[:, :, 4] = 0.0  # a zero column: its scale is 1
    gram = torch.as_tensor(np.einsum("dsi,dsj->dij", a, a))
    balanced = BalancedGram(gram, 200, 9)
    # two jobs of three columns (gathered together; one unsorted), and a single
    # problem on its own columns (no gather) in the loop below
    jobs = [
        ([0, 1, 2, 3, 5, 6], 7, -1.0),
        ([1, 4, 8], 0, 1.0),
        ([2, 3], 6, -1.0),
        ([6, 2, 3], 1, 1.0),
    ]
    pairs, union, block = balanced.problems(jobs)
    np.testing.assert_array_equal(union, [0, 1, 2, 3, 4, 5, 6, 8])
    assert torch.equal(block, balanced.block(union)[0])
    w = torch.as_tensor(rng.standard_normal(6))
    for (free, target, sign), (datafit, to_coef) in zip(jobs, pairs):
        # each job scaled on its own: the same values bit for bit
        g, s = balanced.block(free)
        y = balanced.target_scale(target)
        assert torch.equal(datafit.gram, g)
        assert torch.equal(datafit.rhs, sign * balanced.gram[free, target] / (s * y))
        assert datafit.const == 1.0
        assert torch.equal(to_coef(w[: len(free)]), w[: len(free)] * y / s)
        alone = balanced.problem(free, target, sign)[0]
        assert torch.equal(alone.gram, g) and torch.equal(alone.rhs, datafit.rhs)
    with pytest.raises(ValueError, match="identically zero"):
        balanced.problems([([0, 1], 4, 1.0)])
