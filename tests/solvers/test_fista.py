"""FISTA (lagsindy.solvers.fista and its one loop, lagsindy.solvers._loop): closed
forms, scikit-learn's Lasso, the KKT certificate, the divergence guard, and one
problem, a batch and the tensor path running the same iterations."""

import importlib

import numpy as np
import pytest
import torch
from lasso_problems import (
    TensorGram,
    gram_problem,
    known_lasso,
    random_gram,
    solve_stacked,
)
from sklearn.linear_model import Lasso

from lagsindy.solvers import L1, GramQuadratic, fista, fista_batch

loop = importlib.import_module("lagsindy.solvers._loop")


# ------------------------------------------------------------ one problem
@pytest.mark.parametrize("lam", [0.01, 0.1])
def test_fista_matches_sklearn_lasso(lam):
    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 15))
    w_true = np.zeros(15)
    w_true[[1, 4, 9]] = [2.0, -1.0, 0.5]
    y = A @ w_true + 0.1 * rng.normal(size=200)
    res = fista(gram_problem(A, y), L1(lam), tol=1e-10, max_iter=100_000)
    ref = Lasso(alpha=lam, fit_intercept=False, tol=1e-12, max_iter=100_000).fit(A, y)
    # the certificate: the KKT distance below the tolerance asked
    assert res.converged and res.stop_crit < 1e-10
    np.testing.assert_allclose(res.coef.numpy(), ref.coef_, atol=1e-7)


def test_orthonormal_design_gives_soft_thresholding():
    rng = np.random.default_rng(1)
    n, p = 50, 6
    Q, _ = np.linalg.qr(rng.normal(size=(n, p)))
    A = Q * np.sqrt(n)  # A^T A / n = I
    y = rng.normal(size=n)
    lam = 0.3
    res = fista(gram_problem(A, y), L1(lam), tol=1e-12)
    z = A.T @ y / n
    np.testing.assert_allclose(
        res.coef.numpy(), np.sign(z) * np.maximum(np.abs(z) - lam, 0), atol=1e-10
    )


def test_lam_above_lam_max_gives_exact_zeros():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(80, 5))
    y = rng.normal(size=80)
    lam_max = np.abs(A.T @ y / 80).max()
    res = fista(gram_problem(A, y), L1(lam_max * 1.0001), tol=1e-12)
    assert np.all(res.coef.numpy() == 0.0)
    res = fista(gram_problem(A, y), L1(lam_max * 0.9), tol=1e-12)
    assert np.count_nonzero(res.coef.numpy()) >= 1


def test_unpenalized_weight_is_not_shrunk():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(100, 4))
    y = A @ np.array([1.0, 0.0, 0.0, 0.0])
    weights = torch.tensor([0.0, 1.0, 1.0, 1.0], dtype=torch.float64)
    res = fista(gram_problem(A, y), L1(10.0, weights), tol=1e-12)
    # lam is huge: every penalised coefficient is zero, the free one is the LS value
    np.testing.assert_allclose(res.coef.numpy(), [1.0, 0, 0, 0], atol=1e-9)


def test_converges_on_ill_conditioned_problem():
    rng = np.random.default_rng(4)
    base = rng.normal(size=(300, 1))
    A = np.concatenate(
        [
            base + 1e-3 * rng.normal(size=(300, 1)),
            base + 1e-3 * rng.normal(size=(300, 1)),
            rng.normal(size=(300, 3)),
        ],
        axis=1,
    )
    y = A @ np.array([1.0, 1.0, 0.5, 0.0, 0.0])
    df = gram_problem(A, y)
    ev = torch.linalg.eigvalsh(df.gram)
    assert float(ev[-1] / ev[0]) > 1e5
    lam = 1e-4
    res = fista(df, L1(lam), tol=1e-14, max_iter=500_000)
    assert res.converged
    w = res.coef.numpy()
    # Closed form on the support with its signs: G_SS w_S = b_S - lam * sign(w_S)
    s = np.flatnonzero(w)
    g, b = df.gram.numpy(), df.rhs.numpy()
    w_closed = np.linalg.solve(g[np.ix_(s, s)], b[s] - lam * np.sign(w[s]))
    np.testing.assert_allclose(w[s], w_closed, atol=1e-6)
    # and the zero coefficients satisfy the KKT inequality
    grad = g @ w - b
    off = np.setdiff1d(np.arange(5), s)
    assert np.all(np.abs(grad[off]) <= lam + 1e-9)
    # no worse than scikit-learn's coordinate descent on the same objective
    ref = Lasso(alpha=lam, fit_intercept=False, tol=1e-14, max_iter=10_000)
    with pytest.warns(Warning):
        ref.fit(A, y)
    obj = df.value(res.coef) + L1(lam).value(res.coef)
    obj_ref = df.value(torch.tensor(ref.coef_)) + L1(lam).value(torch.tensor(ref.coef_))
    assert obj <= obj_ref + 1e-12


def test_divergent_step_is_reduced():
    rng = np.random.default_rng(5)
    A = rng.normal(size=(100, 5))
    y = A @ np.array([1.0, -2.0, 0.0, 0.0, 3.0])
    df = gram_problem(A, y)
    res = fista(df, L1(1e-3), step=50.0 / df.lipschitz(), tol=1e-10, max_iter=50_000)
    assert res.step_reductions > 0
    assert res.converged
    np.testing.assert_allclose(res.coef.numpy(), [1.0, -2.0, 0, 0, 3.0], atol=1e-2)


def test_a_step_above_two_over_l_is_halved_below_it_at_once():
    """Just above 2/L: halved once; at 2/L and below: kept; far above: halved as
    many times as needed, before iterating (not found by diverging)."""
    lip = 3.0
    steps, halvings = loop.initial_steps(
        np.array([1e6, 2.0 * (1 + 1e-9), 2.0, 1.5]) / lip, lip, 4
    )
    np.testing.assert_array_equal(halvings, [19, 1, 0, 0])
    np.testing.assert_allclose(steps * lip, [1e6 / 2**19, 1.0 + 1e-9, 2.0, 1.5])
    default, none = loop.initial_steps(None, lip, 1)
    assert default[0] == 1 / lip and none[0] == 0


class _Bumpy(TensorGram):
    """Reports its objective 1.0 too high at the given calls of ``value`` (the
    first is the start, the next ones FISTA's checks)."""

    def __init__(self, *args, bumps):
        super().__init__(*args)
        self.bumps, self.calls = set(bumps), 0

    def value(self, w):
        self.calls += 1
        return super().value(w) + (1.0 if self.calls in self.bumps else 0.0)


@pytest.mark.parametrize(
    "bumps, halvings", [((2,), 0), ((2, 4), 0), ((2, 3), 1), ((3, 4, 5), 1)]
)
def test_two_rises_in_a_row_halve_the_step(bumps, halvings):
    """The divergence guard: one rise of the objective, or two apart, leave the
    step alone; two checks in a row above the best halve it (once: the count of
    rises starts again)."""
    G, b, lam, x = known_lasso()
    datafit = _Bumpy(torch.tensor(G), torch.tensor(b), 0.0, bumps=bumps)
    res = fista(datafit, L1(lam), tol=1e-8, max_iter=100_000)
    assert res.converged and res.step_reductions == halvings
    # measured: 1.6e-4 (the KKT tolerance on the collinear pair), 2.0e-5 halved
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=5e-4)


def test_an_infeasible_warm_start_is_projected_first():
    """A start below zero on a non-negative coordinate is projected before the exact
    finish of its own signs could end the run there (it did: (1, -0.5) came back
    as converged after 0 iterations)."""
    a = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=torch.float64)
    y = a @ torch.tensor([1.0, -0.5], dtype=torch.float64)
    datafit = GramQuadratic(a.T @ a, a.T @ y, float(y @ y))
    nonneg = torch.tensor([False, True])
    start = torch.tensor([1.0, -0.5], dtype=torch.float64)
    # with w1 = 0 held, w0 fits (y0 + y2) / 2 = 0.75, less lam / 2
    want = np.array([0.75 - 5e-7, 0.0])
    res = fista(datafit, L1(1e-6, None, nonneg), start, tol=1e-12)
    np.testing.assert_allclose(res.coef.numpy(), want, rtol=0, atol=1e-12)
    out = fista_batch(datafit.gram.numpy(), datafit.rhs.numpy()[None],
                      np.array([datafit.const]), 1e-6, np.ones((1, 2)),
                      start.numpy()[None], np.ones((1, 2), bool),
                      nonneg.numpy()[None], tol=1e-12)  # fmt: skip
    np.testing.assert_allclose(out.coef[0], want, rtol=0, atol=1e-12)


def test_contract_errors_name_missing_methods():
    class Broken:
        n_features = 2
        rhs = torch.zeros(2)

    with pytest.raises(AttributeError, match="lacks"):
        fista(Broken(), L1(0.1))


def test_a_datafit_without_lipschitz_constant_needs_a_step():
    G, b, lam, x = known_lasso()

    class NoConstant(TensorGram):
        def lipschitz(self):
            return None

    datafit = NoConstant(torch.tensor(G), torch.tensor(b), 0.0)
    with pytest.raises(ValueError, match="needs a step.*proximal_gradient"):
        fista(datafit, L1(lam))
    step = 1.0 / np.linalg.eigvalsh(G)[-1]
    res = fista(datafit, L1(lam), step=step, tol=1e-9, max_iter=100_000)
    assert res.converged
    # measured 1.6e-5: the KKT tolerance along the nearly collinear direction
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=5e-5)


def test_fista_ends_on_the_exact_minimiser_of_a_steady_support():
    G, b, lam, x = known_lasso()
    datafit = GramQuadratic(torch.tensor(G), torch.tensor(b), 0.0)
    res = fista(datafit, L1(lam), tol=1e-8)
    assert res.converged
    # measured: 20 iterations, error 7e-14 (condition number of G 3.1e4)
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=1e-10)
    # the same iterations on tensors (no exact finish) take far longer
    plain = fista(TensorGram(datafit.gram, datafit.rhs, 0.0), L1(lam), tol=1e-8,
                  max_iter=100_000)  # fmt: skip
    # measured: 1150 iterations, and stopped 1.6e-4 away from the minimiser (its
    # KKT distance is below tol along the nearly collinear direction)
    assert plain.converged
    assert res.n_iter * 20 < plain.n_iter
    assert np.abs(plain.coef.numpy() - x).max() > 1e-6


@pytest.mark.parametrize("constrained", [False, True])
def test_numpy_and_tensor_problems_run_the_same_iterations(monkeypatch, constrained):
    """One loop: without the exact finishes (which need NumPy), a Gram quadratic on
    NumPy arrays and the same problem through the tensor contract take the same
    iterations to the same point (only the products' rounding differs)."""
    G, b, lam, x = known_lasso()
    weights = torch.linspace(0.5, 1.5, x.size, dtype=torch.float64)
    nonneg = torch.tensor(x > 0) if constrained else None
    penalty = L1(lam, weights, nonneg)
    tensors = fista(TensorGram(torch.tensor(G), torch.tensor(b), 0.0), penalty,
                    tol=1e-8, max_iter=100_000)  # fmt: skip
    monkeypatch.setattr(loop.GramRows, "exact", False)
    arrays = fista(GramQuadratic(torch.tensor(G), torch.tensor(b), 0.0), penalty,
                   tol=1e-8, max_iter=100_000)  # fmt: skip
    # measured: 1150 and 1350 iterations each way
    assert arrays.n_iter == tensors.n_iter > 1000
    assert arrays.stop_crit == pytest.approx(tensors.stop_crit, rel=1e-6)
    # measured 1.6e-13 and 6.7e-11 (nearly collinear columns amplify the rounding)
    np.testing.assert_allclose(arrays.coef, tensors.coef, rtol=0, atol=3e-10)


def test_float32_problem_iterates_in_float32():
    G, b, lam, x = known_lasso(collinear=0.5)
    datafit = GramQuadratic(torch.tensor(G, dtype=torch.float32),
                            torch.tensor(b, dtype=torch.float32), 0.0)  # fmt: skip
    res = fista(datafit, L1(lam), tol=1e-5)
    assert res.converged and res.coef.dtype == torch.float32
    # float32 rounding of the exact minimiser: at most 1.8e-7 here, measured 1.2e-8
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=2e-7)


# ------------------------------------------------------------------ batches
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
    grams, rhss, consts = zip(*[random_gram(rng, 300, p) for _ in range(n_prob)])
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
    # the problems stop at different iterations: the lockstep and the last running
    # problem going on alone (on its own coordinates) are exercised
    assert len(set(iters)) > 2


def test_fista_batch_halves_a_step_above_two_over_l():
    rng = np.random.default_rng(1)
    gram, rhs, const = random_gram(rng, 200, 6)
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


def test_fista_batch_ends_on_the_exact_minimisers():
    problems = [known_lasso(seed=s) for s in range(3)]
    res = solve_stacked(problems)
    assert res.converged.all()
    for r, (_, _, _, x) in enumerate(problems):
        np.testing.assert_allclose(res.coef[r], x, rtol=0, atol=1e-10)
    assert res.n_iter.max() <= 100  # measured 20 each (plain FISTA: ~1000)


def test_batch_divergence_guard_names_the_step(monkeypatch):
    """Two rises of the objective in a row halve a row's step (the guard of every
    row); a guard that is spent raises, naming the halvings and the step."""
    rng = np.random.default_rng(2)
    gram, rhs, const = random_gram(rng, 200, 6, collinear=1.0)
    lip = np.linalg.eigvalsh(gram)[-1]
    args = (gram, np.stack([rhs, rhs]), np.array([const, const]), 1e-3,
            np.ones((2, 6)), np.zeros((2, 6)), np.ones((2, 6), bool))  # fmt: skip
    # below 2/L, so not halved at once; FISTA's momentum diverges there
    steps = np.array([1.0 / lip, 1.99 / lip])
    res = fista_batch(*args, step=steps, tol=1e-9)
    assert res.converged.all()
    assert res.step_reductions[0] == 0 < res.step_reductions[1]  # measured 0, 1
    # both end on the exact minimiser (measured: equal)
    np.testing.assert_allclose(res.coef[1], res.coef[0], rtol=0, atol=1e-12)
    with pytest.raises(FloatingPointError, match=r"halved 0 times.*alpha"):
        fista_batch(*args, step=steps, tol=1e-9, max_step_reductions=0)
