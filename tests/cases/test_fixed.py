"""lagsindy.cases.fixed (case III): the shortlist's scores against one operator per
model, reused first starts, the ranking that solves only the candidates that can be
shortlisted, and the tie rule among the scored models."""

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from lagsindy.cases import fixed
from lagsindy.cases.fixed import acceleration_r2s
from lagsindy.formulation.operator import forward_accelerations
from lagsindy.formulation.scaling import fixed_term_bounds


def _r2_one_operator(p, coef, Xt):
    """The former scoring: one operator per model."""
    from sklearn.metrics import r2_score

    support = np.flatnonzero(coef)
    op = p.feature_operator(support, Xt.device, Xt.dtype)
    c = torch.as_tensor(coef[support], dtype=Xt.dtype, device=Xt.device)
    pred = forward_accelerations(op, c, Xt, None).numpy()
    true = Xt[:, 2 * p.n_dof : 3 * p.n_dof].numpy()
    return r2_score(true, pred, multioutput="variance_weighted")


def test_shortlist_scores_equal_one_operator_per_model(case_iii_problem):
    p = case_iii_problem
    free = np.flatnonzero(p.identifiable)
    coefs = []
    for r in free[:4]:
        others = np.array([k for k in free if k != r])
        coef, _ = p.solver.solve(p.balanced, others, r, -1.0, p.penalty, 1.0, 0)
        coef[r] = 1.0
        coefs.append(coef)
    Xs = p.Xt[:500]
    broken = coefs[0].copy()
    broken[np.flatnonzero(broken)[0]] = np.nan  # its accelerations are not finite
    got = acceleration_r2s(p, coefs + [np.zeros(p.n_features), broken], Xs)
    assert got.pop() == -np.inf
    want = [_r2_one_operator(p, c, Xs) for c in coefs]
    assert got[-1] == -np.inf
    # measured: equal to 1e-15; the supports differ, so a mix-up shows at 1e-2
    np.testing.assert_allclose(got[:-1], want, rtol=1e-12, atol=1e-12)
    assert len({round(g, 6) for g in got[:-1]}) > 1  # the models do score differently


def test_scores_of_singular_mass_matrices_equal_one_operator(case_iii_problem):
    """Models whose mass matrix is singular on every row (one velocity squared,
    or the square of a sum of velocities) score through the pseudo-inverse,
    beside regular ones in the same batch, as one operator per model scores them."""
    p = case_iii_problem
    names = list(p.names)
    rng = np.random.default_rng(0)
    coefs = []
    for kinetic in ("x_dot**2", "theta_dot**2"):
        coef = np.zeros(p.n_features)
        coef[names.index(kinetic)] = 1.0
        coef[names.index("cos(theta)")] = 9.81
        coefs.append(coef)
    coef = np.zeros(p.n_features)  # (x_dot + theta_dot)**2: rank one
    for name, value in (("x_dot**2", 1.0), ("theta_dot*x_dot", 2.0)):
        coef[names.index(name)] = value
    coef[names.index("theta_dot**2")] = 1.0
    coef[names.index("cos(theta)")] = 9.81
    coefs.append(coef)
    coefs.append(rng.standard_normal(p.n_features) * (rng.random(p.n_features) < 0.3))
    Xs = p.Xt[:500]
    got = acceleration_r2s(p, coefs, Xs)
    want = [_r2_one_operator(p, c, Xs) for c in coefs]
    # measured: equal to 2e-16 (the last model, R2 = -6514: 2e-14 relative)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", ["single_pendulum", "triple_pendulum"])
def test_scores_of_one_and_three_dof_models_equal_one_operator(name):
    """Other sizes than two degrees of freedom score through pinv_solve."""
    from _helpers import first_problem

    from lagsindy import CandidateLibrary, LagrangianSINDy
    from lagsindy.systems import get_system, make_dataset

    system = get_system(name)
    data = make_dataset(system, n_trajectories=2, excitation=None, random_state=0)
    # the Lagrangian's own terms and a few others (the paper's triple pendulum
    # library, 222 terms, takes 20 s to fit)
    first = system.coordinates[0]
    terms = list(system.terms()) + [f"sin({first})", f"sin({first})**2"]
    library = CandidateLibrary.from_terms(system.coordinates, terms)
    p = first_problem(LagrangianSINDy(library), data.X[:400])
    rng = np.random.default_rng(1)
    coefs = [
        rng.standard_normal(p.n_features) * (rng.random(p.n_features) < 0.4)
        for _ in range(3)
    ]
    coefs[0][:] = 0.0  # the true Lagrangian, in the library's terms
    coefs[0][: len(library)] = system.true_coefficients(library)
    Xs = p.Xt[:300]
    got = acceleration_r2s(p, coefs, Xs)
    want = [_r2_one_operator(p, c, Xs) for c in coefs]
    # measured: equal to 1e-15 relative (a sign flip of the residual cannot show:
    # the squared errors do not depend on it)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert got[0] > 0.99  # the true model predicts the accelerations


@pytest.mark.slow  # 20 s; test_lockstep_solves checks the batched search's reuse
def test_first_start_result_stands_for_the_first_start(case_iii_problem):
    """solve(first=<starts=1 result>) equals a fresh solve, restarts included."""
    p = case_iii_problem
    free = np.flatnonzero(p.identifiable)
    restarted = 0
    for r in free:
        others = np.array([k for k in free if k != r])
        args = (p.balanced, others, r, -1.0, p.penalty, 1.0, 0)
        fresh, fresh_res = p.solver.solve(*args)
        _, ranked = p.solver.solve(*args, starts=1)
        reused, reused_res = p.solver.solve(*args, first=ranked)
        np.testing.assert_array_equal(reused, fresh)
        assert reused_res.cost == fresh_res.cost
        assert len(reused_res.stages) == len(fresh_res.stages)
        for a, b in zip(reused_res.stages, fresh_res.stages):
            np.testing.assert_array_equal(a.coef, b.coef)
            np.testing.assert_array_equal(a.support, b.support)
        restarted += reused_res is not ranked
    assert restarted > 0  # some candidates need the second start on these data


def _symmetric_cases(n, seed=0):
    """Symmetric n x n matrices: generic, indefinite, singular, zero, rank one."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(600, n, n, dtype=torch.float64, generator=g)
    m = a @ a.transpose(1, 2)
    m[:100] -= 2 * torch.eye(n, dtype=torch.float64)  # indefinite
    m[100:200, -1, :] = 0  # singular, with exact zeros (a model without a velocity)
    m[100:200, :, -1] = 0
    m[200:220] = 0
    v = torch.randn(100, n, dtype=torch.float64, generator=g)
    m[300:400] = 3 * v[:, :, None] * v[:, None, :]  # rank one
    m[400:450, 0, 0] = m[400:450, -1, -1]  # equal diagonal
    m[450:500, 0, 0] = -m[450:500, -1, -1]  # zero trace (n = 2)
    m = 0.5 * (m + m.transpose(1, 2))
    return m, torch.randn(600, n, dtype=torch.float64, generator=g)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_pinv_solve_equals_torch_pinv(n):
    from lagsindy.cases.fixed import pinv_solve

    m, b = _symmetric_cases(n)
    want = (torch.linalg.pinv(m, hermitian=True) @ b.unsqueeze(-1)).squeeze(-1)
    got = pinv_solve(m, b)
    size = want.abs().amax(-1).clamp(min=1e-300)
    err = (got - want).abs().amax(-1) / size
    cond = torch.linalg.cond(m)
    ok = torch.isfinite(cond)
    # measured (n = 2): error / (cond * eps) <= 1.44, i.e. the rounding of either
    # method; exactly singular (zero rows) and zero matrices agree exactly
    assert float((err[ok] / (cond[ok] * 2.2e-16)).max()) < 50
    assert torch.equal(got[100:220].abs() > 0, want[100:220].abs() > 0)
    torch.testing.assert_close(got[100:220], want[100:220], rtol=1e-12, atol=0)
    # a sign flip or a missing 1/lambda in one eigen-direction shows at O(1)
    assert float(err[220:300].max()) < 1e-9
    # A batch of well-conditioned matrices only (n = 2: Cramer's rule throughout)
    alone = pinv_solve(m[220:300], b[220:300])
    err = (alone - want[220:300]).abs().amax(-1) / size[220:300]
    assert float((err / (cond[220:300] * 2.2e-16)).max()) < 50
    if n <= 2:  # closed forms, element by element: the same bits in any batch
        torch.testing.assert_close(alone, got[220:300], rtol=0, atol=0)
    else:  # LAPACK, whose kernels may depend on the batch's size and alignment
        torch.testing.assert_close(alone, got[220:300], rtol=1e-12, atol=0)


def test_r2_scores_equal_sklearn():
    from sklearn.metrics import r2_score

    from lagsindy.cases.fixed import r2_scores

    rng = np.random.default_rng(0)
    true = rng.standard_normal((300, 2)) * [1.0, 5.0]
    pred = true + 0.3 * rng.standard_normal((4, 300, 2))
    pred[1, :, 0] = true[:, 0]  # one output predicted exactly
    constant = true.copy()
    constant[:, 1] = 2.0  # an output without variance, predicted exactly or not
    for t, p in ((true, pred), (constant, pred), (np.ones((300, 2)), pred)):
        p = p.copy()
        p[0, :, 1] = t[:, 1]
        want = [r2_score(t, x, multioutput="variance_weighted") for x in p]
        # measured: equal to 2e-16
        np.testing.assert_allclose(r2_scores(t, p), want, rtol=0, atol=1e-13)
    p = np.ones((2, 300, 2))
    p[1, 0, 0] = 2.0
    want = [r2_score(np.ones((300, 2)), x, multioutput="variance_weighted") for x in p]
    np.testing.assert_array_equal(r2_scores(np.ones((300, 2)), p), want)


def test_mass_traces_are_computed_once_per_fit(monkeypatch, case_iii_problem):
    """The windows of a weak-form search share the mass-matrix traces (p.memo)."""
    import warnings

    from lagsindy import LagrangianSINDy
    from lagsindy.cases import fixed
    from lagsindy.systems import cart_pendulum, make_dataset

    p = case_iii_problem
    rows = p.solver.subsample_rows(p.Xt.shape[0], fixed.SELECTION_ROWS)
    fresh = fixed._mass_traces(p, rows)
    got = fixed.mass_traces(p)
    np.testing.assert_array_equal(got, fresh)
    got[:] = 0.0  # a copy: the memo keeps its own
    np.testing.assert_array_equal(fixed.mass_traces(p), fresh)

    calls, solves = [], []
    original, solve = fixed._mass_traces, fixed.solve_mass
    monkeypatch.setattr(
        fixed, "_mass_traces", lambda *a: calls.append(1) or original(*a)
    )
    monkeypatch.setattr(fixed, "solve_mass", lambda *a: solves.append(1) or solve(*a))
    system = cart_pendulum()
    data = make_dataset(system, n_trajectories=6, excitation=None, random_state=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = LagrangianSINDy(system.paper_library(), fixed_term="mass").fit(
            data.X, groups=data.groups
        )
    assert est.formulation_ == "weak"
    assert len(solves) >= 2  # two windows were solved (the second checks the first)
    assert len(calls) == 1


def test_evenly_spaced_subsample_rows(case_iii_problem):
    solver = dataclasses.replace(case_iii_problem.solver, random_state=None)
    for n, size in [(10, 20), (4001, 4000), (4003, 4000), (123457, 4000), (7, 3)]:
        rows = solver.subsample_rows(n, size)
        want = np.unique(np.linspace(0, n - 1, size).round().astype(np.int64))
        np.testing.assert_array_equal(rows, np.arange(n) if n <= size else want)
        assert rows.size == min(n, size)  # no repeats were there to drop


def test_search_scores_on_the_scoring_subsample():
    """The search scores its shortlist on SCORING_ROWS rows (2000, as many as the
    fit's own acceleration check), not on the traces' SELECTION_ROWS."""
    from _helpers import first_problem

    from lagsindy import LagrangianSINDy, model
    from lagsindy.cases import fixed
    from lagsindy.systems import cart_pendulum, make_dataset

    system = cart_pendulum()
    data = make_dataset(system, n_trajectories=6, excitation=None, random_state=0)
    p = first_problem(
        LagrangianSINDy(system.paper_library()), data.X, groups=data.groups
    )
    assert model.ACCELERATION_ROWS == fixed.SCORING_ROWS == 2000
    assert p.Xt.shape[0] > fixed.SCORING_ROWS  # a subsample is drawn
    solution = fixed.fit_fixed(p)
    rows = p.solver.subsample_rows(p.Xt.shape[0], fixed.SCORING_ROWS)
    want = fixed.acceleration_r2s(p, [solution.coef], p.Xt[torch.as_tensor(rows)])[0]
    assert solution.score == want


# ----------------------------- the ranking: only candidates that can be shortlisted
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
    from _helpers import first_problem

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


# ------------------------------------------------------------------- the tie rule
def _scored(r2, n_terms, kind="term", r=0):
    """A shortlisted model as case III's search scores it."""
    coef = np.zeros(8)
    coef[:n_terms] = 1.0
    return (r2, kind, r, coef, None)


@pytest.mark.parametrize(
    "ratio, sparse_wins",
    [
        (1.0, True),
        (1.05, True),
        (fixed.SELECTION_TIE * (1 - 1e-6), True),
        (fixed.SELECTION_TIE * (1 + 1e-6), False),
        (1.15, False),  # between the tie band and twice it
        (1.19, False),
    ],
)
def test_a_sparser_model_within_the_tie_band_wins(ratio, sparse_wins):
    """The best model leaves 0.1 of the acceleration variance unexplained; a sparser
    one leaving ``ratio`` times that is kept when ``ratio <= SELECTION_TIE``."""
    best = _scored(0.9, 5, r=1)
    sparse = _scored(1 - ratio * 0.1, 2, r=3)
    assert fixed.pick_scored([best, sparse]) is (sparse if sparse_wins else best)
    assert fixed.pick_scored([sparse, best]) is (sparse if sparse_wins else best)


def test_ties_go_to_the_mass_normalization_then_the_earlier_term():
    a, b = _scored(0.9, 2, r=4), _scored(0.905, 2, r=2)
    mass = _scored(0.9, 2, kind="mass", r=6)
    assert fixed.pick_scored([a, b]) is b
    assert fixed.pick_scored([a, b, mass]) is mass
    # not a tie: the best wins whatever its size
    dense = _scored(0.99, 7, r=5)
    assert fixed.pick_scored([a, b, mass, dense]) is dense
