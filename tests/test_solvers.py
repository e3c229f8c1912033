import numpy as np
import pytest
import torch
from _lasso_problems import known_lasso, solve_stacked
from sklearn.linear_model import Lasso

from lagsindy.solvers import (
    L1,
    BalancedGram,
    GramQuadratic,
    fista,
    fista_path,
    staged_fista,
)


def _gram_problem(A, y):
    n = A.shape[0]
    A, y = torch.tensor(A), torch.tensor(y)
    return GramQuadratic(A.T @ A / n, A.T @ y / n, float(y @ y / n))


@pytest.mark.parametrize("lam", [0.01, 0.1])
def test_fista_matches_sklearn_lasso(lam):
    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 15))
    w_true = np.zeros(15)
    w_true[[1, 4, 9]] = [2.0, -1.0, 0.5]
    y = A @ w_true + 0.1 * rng.normal(size=200)
    res = fista(_gram_problem(A, y), L1(lam), tol=1e-10, max_iter=100_000)
    ref = Lasso(alpha=lam, fit_intercept=False, tol=1e-12, max_iter=100_000).fit(A, y)
    assert res.converged and res.stop_crit < 1e-10
    np.testing.assert_allclose(res.coef.numpy(), ref.coef_, atol=1e-7)


def test_orthonormal_design_gives_soft_thresholding():
    rng = np.random.default_rng(1)
    n, p = 50, 6
    Q, _ = np.linalg.qr(rng.normal(size=(n, p)))
    A = Q * np.sqrt(n)  # A^T A / n = I
    y = rng.normal(size=n)
    lam = 0.3
    res = fista(_gram_problem(A, y), L1(lam), tol=1e-12)
    z = A.T @ y / n
    np.testing.assert_allclose(
        res.coef.numpy(), np.sign(z) * np.maximum(np.abs(z) - lam, 0), atol=1e-10
    )


def test_lam_above_lam_max_gives_exact_zeros():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(80, 5))
    y = rng.normal(size=80)
    lam_max = np.abs(A.T @ y / 80).max()
    res = fista(_gram_problem(A, y), L1(lam_max * 1.0001), tol=1e-12)
    assert np.all(res.coef.numpy() == 0.0)
    res = fista(_gram_problem(A, y), L1(lam_max * 0.9), tol=1e-12)
    assert np.count_nonzero(res.coef.numpy()) >= 1


def test_unpenalized_weight_is_not_shrunk():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(100, 4))
    y = A @ np.array([1.0, 0.0, 0.0, 0.0])
    weights = torch.tensor([0.0, 1.0, 1.0, 1.0], dtype=torch.float64)
    res = fista(_gram_problem(A, y), L1(10.0, weights), tol=1e-12)
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
    df = _gram_problem(A, y)
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
    df = _gram_problem(A, y)
    res = fista(df, L1(1e-3), step=50.0 / df.lipschitz(), tol=1e-10, max_iter=50_000)
    assert res.step_reductions > 0
    assert res.converged
    np.testing.assert_allclose(res.coef.numpy(), [1.0, -2.0, 0, 0, 3.0], atol=1e-2)


def test_contract_errors_name_missing_methods():
    class Broken:
        n_features = 2
        rhs = torch.zeros(2)

    with pytest.raises(AttributeError, match="lacks"):
        fista(Broken(), L1(0.1))


def test_staged_schedule_removes_small_terms_and_debiases():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(500, 8))
    w_true = np.array([3.0, 0.0, -2.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    y = A @ w_true + 0.01 * rng.normal(size=500)
    res = staged_fista(
        _gram_problem(A, y), lam=0.05, threshold=0.05, tol=0.0, max_stages=3
    )
    np.testing.assert_array_equal(res.support, [0, 2, 7])
    # debiased: the least-squares fit of the support, no L1 shrinkage left (the
    # refit solves the Gram matrix, lstsq an SVD of the rows: measured 4.4e-15 here,
    # 0.9e-15 to 3.1e-15 with other BLAS kernels; without the refit the last stage's
    # lam = 5e-4 leaves 5e-4)
    w_ls = np.linalg.lstsq(A[:, res.support], y, rcond=None)[0]
    np.testing.assert_allclose(res.coef.numpy()[res.support], w_ls, rtol=0, atol=2e-14)
    np.testing.assert_allclose(res.coef.numpy(), w_true, atol=2e-3)  # measured 1.0e-3
    assert res.stages[0].lam == 0.05 and res.stages[1].lam == pytest.approx(0.005)
    no_debias = staged_fista(
        _gram_problem(A, y), lam=0.05, threshold=0.05, debias=False, max_stages=1
    )
    assert np.abs(no_debias.coef.numpy()[0]) < 3.0 - 0.04  # shrunk by the penalty


def test_staged_all_zero_stage_removes_nothing():
    rng = np.random.default_rng(7)
    Q, _ = np.linalg.qr(rng.normal(size=(100, 3)))
    A = Q * 10.0  # orthonormal columns, A^T A / n = I
    y = A @ np.array([1.0, 0.0, 1.0])
    res = staged_fista(_gram_problem(A, y), lam=200.0, threshold=0.05, max_stages=6)
    # lam = 200, 20, 2 are above lam_max = 1: all-zero stages remove nothing
    assert [st.support.size for st in res.stages[:3]] == [3, 3, 3]
    np.testing.assert_array_equal(res.support, [0, 2])
    np.testing.assert_allclose(res.coef.numpy(), [1.0, 0.0, 1.0], atol=1e-9)


def test_fista_path_is_monotone_in_sparsity():
    rng = np.random.default_rng(8)
    A = rng.normal(size=(120, 6))
    y = A @ np.array([2.0, 1.0, 0.5, 0.0, 0.0, 0.0]) + 0.05 * rng.normal(size=120)
    coefs, _ = fista_path(_gram_problem(A, y), [1.0, 0.3, 0.1, 0.01], tol=1e-10)
    counts = (coefs != 0).sum(axis=1)
    assert list(counts) == sorted(counts)
    assert counts[0] < counts[-1]


def test_balanced_gram_is_invariant_to_row_and_column_units():
    rng = np.random.default_rng(9)
    a = rng.normal(size=(200, 2, 4))
    y = a @ np.array([1.0, -1.0, 0.5, 0.0])
    full = np.concatenate([a, y[:, :, None]], axis=2)
    g1 = torch.tensor(np.einsum("sip,siq->ipq", full, full))
    scaled = (
        full * np.array([1.0, 1000.0])[None, :, None] * np.array([1, 7.0, 1, 0.01, 1])
    )
    g2 = torch.tensor(np.einsum("sip,siq->ipq", scaled, scaled))
    d1, _ = BalancedGram(g1, 200, 4).problem(np.arange(4), 4)
    d2, _ = BalancedGram(g2, 200, 4).problem(np.arange(4), 4)
    np.testing.assert_allclose(d1.gram.numpy(), d2.gram.numpy(), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(d1.rhs.numpy(), d2.rhs.numpy(), rtol=1e-9, atol=1e-12)


def test_balanced_gram_projects_an_indefinite_corrected_gram_to_the_nearest_psd():
    """Eigenvalues clamped at 0: the nearest PSD matrix in the Frobenius norm."""
    rng = np.random.default_rng(10)
    Q, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    # a noise correction subtracted too much: one eigenvalue is negative
    corrected = Q @ np.diag([2.0, 1.0, -0.5, 0.3]) @ Q.T
    nearest = Q @ np.diag([2.0, 1.0, 0.0, 0.3]) @ Q.T
    gram = torch.tensor(corrected)[None]  # one coordinate, one sample: no averaging
    raw = BalancedGram(gram, 1, 3, normalize=False)
    np.testing.assert_allclose(raw.gram.numpy(), corrected, atol=1e-15)
    projected = BalancedGram(gram, 1, 3, normalize=False, project_psd=True)
    # measured max deviation 3e-16 (rounding of eigh)
    np.testing.assert_allclose(projected.gram.numpy(), nearest, atol=3e-15)
    # no PSD matrix is closer: random PSD matrices around the result are all farther
    dist = np.linalg.norm(projected.gram.numpy() - corrected)
    assert dist == pytest.approx(0.5, rel=1e-12)
    root = Q @ np.diag(np.sqrt([2.0, 1.0, 0.0, 0.3]))
    for _ in range(200):
        F = root + 0.1 * rng.normal(size=(4, 4))
        assert np.linalg.norm(F @ F.T - corrected) >= dist
    # balanced, over two coordinates: still positive semi-definite after the scaling
    two = torch.tensor(np.stack([corrected, 4.0 * corrected]))
    assert float(torch.linalg.eigvalsh(BalancedGram(two, 10, 3).gram)[0]) < -0.09
    balanced = BalancedGram(two, 10, 3, project_psd=True)
    # zero in exact arithmetic: eigvalsh's rounding is a small multiple of
    # eps * |G| (measured -3e-18, -1.7e-17 and 3e-17 with different BLAS kernels)
    evals = torch.linalg.eigvalsh(balanced.gram)
    assert float(evals[0]) >= -4 * np.finfo(float).eps * float(evals[-1])


@pytest.mark.parametrize("d", [1, 2])
def test_acceleration_datafit_analytic_gradient_equals_autograd(d):
    """Case II's gradient (the adjoint of the per-sample solve) against autograd of
    the loss, for one and two coordinates with symmetric positive term matrices."""
    from lagsindy.solvers import AccelerationDatafit

    g = torch.Generator().manual_seed(d)
    s, p = 50, 6
    half = torch.randn(s, p, d, d, dtype=torch.float64, generator=g)
    mass = half @ half.transpose(2, 3) + 0.5 * torch.eye(d, dtype=torch.float64)
    bias = torch.randn(s, p, d, dtype=torch.float64, generator=g)
    qdd = torch.randn(s, d, dtype=torch.float64, generator=g)
    scale = torch.rand(p, dtype=torch.float64, generator=g) + 0.5
    fit = AccelerationDatafit(mass, bias, qdd, scale)
    w = torch.rand(p, dtype=torch.float64, generator=g)
    wr = w.clone().requires_grad_(True)
    (want,) = torch.autograd.grad(fit._loss(wr), wr)
    # the solve is cached per point: another point's loss first, then w (twice)
    fit.value(w + 0.1)
    # measured: equal to 1e-16 relative
    torch.testing.assert_close(fit.gradient(w), want, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(fit.gradient(w), want, rtol=1e-12, atol=0.0)
    # the prediction: minus M(c)^-1 b(c), per sample
    c = w / scale
    mc = torch.einsum("skij,k->sij", mass, c)
    bc = torch.einsum("ski,k->si", bias, c)
    torch.testing.assert_close(fit.predict(w), -torch.linalg.solve(mc, bc))


# ------------------------------------------------------------ exact finish (polish)
def test_polish_returns_the_minimiser_of_the_right_pattern_only():
    from lagsindy.solvers.exact import _polish

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


class _TensorGram(GramQuadratic):
    """A Gram quadratic that fista iterates through the datafit contract (tensors,
    no exact finishes), as it does a GPU one."""


def test_fista_ends_on_the_exact_minimiser_of_a_steady_support():
    G, b, lam, x = known_lasso()
    datafit = GramQuadratic(torch.tensor(G), torch.tensor(b), 0.0)
    res = fista(datafit, L1(lam), tol=1e-8)
    assert res.converged
    # measured: 20 iterations, error 7e-14 (condition number of G 3.1e4)
    np.testing.assert_allclose(res.coef.numpy(), x, rtol=0, atol=1e-10)
    # the same iterations on tensors (no exact finish) take far longer
    tensors = _TensorGram(datafit.gram, datafit.rhs, 0.0)
    plain = fista(tensors, L1(lam), tol=1e-8, max_iter=100_000)
    # measured: 1150 iterations, and stopped 1.6e-4 away from the minimiser (its
    # KKT distance is below tol along the nearly collinear direction)
    assert plain.converged
    assert res.n_iter * 20 < plain.n_iter
    assert np.abs(plain.coef.numpy() - x).max() > 1e-6


def test_fista_batch_ends_on_the_exact_minimisers():
    problems = [known_lasso(seed=s) for s in range(3)]
    res = solve_stacked(problems)
    assert res.converged.all()
    for r, (_, _, _, x) in enumerate(problems):
        np.testing.assert_allclose(res.coef[r], x, rtol=0, atol=1e-10)
    assert res.n_iter.max() <= 100  # measured 20 each (plain FISTA: ~1000)
