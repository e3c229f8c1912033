"""The staged schedule (lagsindy.solvers.staged, its problems in _problems): stages,
thresholds, the refit, and one problem, a batch and case II's datafit going through
the same schedule."""

import numpy as np
import pytest
import torch
from lasso_problems import TensorGram, gram_problem, random_gram

from lagsindy.solvers import (
    AccelerationDatafit,
    GramQuadratic,
    fista_path,
    staged_fista,
    staged_fista_batch,
)
from lagsindy.solvers import staged as staged_module


def test_staged_schedule_removes_small_terms_and_debiases():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(500, 8))
    w_true = np.array([3.0, 0.0, -2.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    y = A @ w_true + 0.01 * rng.normal(size=500)
    res = staged_fista(
        gram_problem(A, y), lam=0.05, threshold=0.05, tol=0.0, max_stages=3
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
        gram_problem(A, y), lam=0.05, threshold=0.05, debias=False, max_stages=1
    )
    assert np.abs(no_debias.coef.numpy()[0]) < 3.0 - 0.04  # shrunk by the penalty


def test_the_refit_removes_a_term_that_stood_in_for_shrunk_ones():
    """x2 = (x0 + x1) / 2 + noise: the L1 stage keeps it (0.22) to make up for the
    shrinkage of x0 and x1; the refit of {0, 1, 2} leaves it at rounding level, so it
    is removed and {0, 1} refitted."""
    rng = np.random.default_rng(0)
    x0, x1, z, other = rng.standard_normal((4, 400))
    A = np.stack([x0, x1, (x0 + x1) / 2 + 0.05 * z, other], 1)
    res = staged_fista(
        gram_problem(A, x0 + x1), lam=0.3, threshold=0.05, tol=0.0, max_stages=1
    )
    np.testing.assert_array_equal(res.stages[0].support, [0, 1, 2])
    assert res.stages[0].coef[2] > 0.2  # measured 0.224
    np.testing.assert_array_equal(res.support, [0, 1])
    # measured 2e-16: y is exactly x0 + x1
    np.testing.assert_allclose(res.coef.numpy(), [1, 1, 0, 0], rtol=0, atol=1e-13)


def test_staged_all_zero_stage_removes_nothing():
    rng = np.random.default_rng(7)
    Q, _ = np.linalg.qr(rng.normal(size=(100, 3)))
    A = Q * 10.0  # orthonormal columns, A^T A / n = I
    y = A @ np.array([1.0, 0.0, 1.0])
    res = staged_fista(gram_problem(A, y), lam=200.0, threshold=0.05, max_stages=6)
    # lam = 200, 20, 2 are above lam_max = 1: all-zero stages remove nothing
    assert [st.support.size for st in res.stages[:3]] == [3, 3, 3]
    np.testing.assert_array_equal(res.support, [0, 2])
    np.testing.assert_allclose(res.coef.numpy(), [1.0, 0.0, 1.0], atol=1e-9)


def test_the_stages_stop_at_the_residual_tolerance():
    """The schedule ends after the first stage whose thresholded solution has a
    relative residual at most ``tol``: just above the first stage's, one more."""
    rng = np.random.default_rng(8)
    A = rng.normal(size=(300, 6))
    y = A @ np.array([2.0, -1.0, 0.0, 0.0, 0.5, 0.0]) + 0.05 * rng.normal(size=300)
    first = staged_fista(gram_problem(A, y), lam=1e-2, max_stages=1).stages[0].cost
    ends = staged_fista(gram_problem(A, y), lam=1e-2, tol=first)
    assert len(ends.stages) == 1
    goes_on = staged_fista(gram_problem(A, y), lam=1e-2, tol=first * (1 - 1e-9))
    assert len(goes_on.stages) > 1


def test_the_threshold_is_relative_to_the_reference_when_larger():
    """Case III's fixed term (``reference``, in the variables' units) sets the
    threshold's scale when it exceeds the largest coefficient: 0.3 is kept against
    the largest (1.0) at threshold 0.05, dropped against a reference of 10."""
    rng = np.random.default_rng(9)
    A = rng.normal(size=(300, 4))
    y = A @ np.array([1.0, 0.3, 0.0, 0.0]) + 0.01 * rng.normal(size=300)
    kept = staged_fista(gram_problem(A, y), lam=1e-3, reference=0.0)
    np.testing.assert_array_equal(kept.support, [0, 1])
    dropped = staged_fista(gram_problem(A, y), lam=1e-3, reference=10.0)
    np.testing.assert_array_equal(dropped.stages[0].support, [0])


def test_fista_path_is_monotone_in_sparsity():
    rng = np.random.default_rng(8)
    A = rng.normal(size=(120, 6))
    y = A @ np.array([2.0, 1.0, 0.5, 0.0, 0.0, 0.0]) + 0.05 * rng.normal(size=120)
    coefs, _ = fista_path(gram_problem(A, y), [1.0, 0.3, 0.1, 0.01], tol=1e-10)
    counts = (coefs != 0).sum(axis=1)
    assert list(counts) == sorted(counts)
    assert counts[0] < counts[-1]


def test_case_ii_datafit_goes_through_the_same_schedule():
    """Case II's non-convex datafit (no Lipschitz constant): proximal-gradient
    stages, the same thresholds, and the local refit from the stage's solution."""
    g = torch.Generator().manual_seed(0)
    s, p = 300, 5
    mass = torch.zeros(s, p, 1, 1, dtype=torch.float64)
    mass[:, 0] = 1.0  # a constant inertia and a varying one
    mass[:, 2] = torch.rand(s, 1, 1, generator=g, dtype=torch.float64) + 0.5
    bias = torch.randn(s, p, 1, dtype=torch.float64, generator=g)
    c = torch.tensor([1.0, 0.0, 0.5, -2.0, 0.0], dtype=torch.float64)
    qdd = -torch.linalg.solve(
        torch.einsum("skij,k->sij", mass, c), torch.einsum("ski,k->si", bias, c)
    )
    datafit = AccelerationDatafit(mass, bias, qdd, torch.ones(p, dtype=torch.float64))
    w0 = torch.tensor([1.0, 0.2, 0.4, -1.5, 0.1], dtype=torch.float64)
    res = staged_fista(datafit, lam=1e-3, threshold=0.05, w0=w0 / w0.norm())
    np.testing.assert_array_equal(res.support, [0, 2, 3])
    w = res.coef.numpy()
    # measured 4.7e-10 (the refit's relative-change tolerance)
    np.testing.assert_allclose(w / w[0], c.numpy(), rtol=0, atol=3e-9)
    # the stages' records: proximal gradient's step and relative change
    assert res.stages[0].converged and res.stages[0].stop_crit < 1e-7


# ------------------------------------------------------------------- batches
def test_staged_fista_batch_equals_staged_fista():
    rng = np.random.default_rng(2)
    p = 10
    datafits, weights, thresholds = [], [], []
    for n_true in range(1, 6):
        g, b, c = random_gram(rng, 400, p, n_true=n_true)
        datafits.append(GramQuadratic(torch.tensor(g), torch.tensor(b), c))
        weights.append(torch.ones(p, dtype=torch.float64))
        thresholds.append(torch.full((p,), 0.1, dtype=torch.float64))
    weights[1][0] = 0.0  # an unpenalised feature
    even = torch.arange(p) % 2 == 0
    nonneg = [None, even, even, None, even]
    settings = dict(lam=1e-2, reference=0.0, tol=1e-6, solver_tol=1e-9)
    got = staged_fista_batch(
        datafits,
        penalty_weights=weights,
        threshold=thresholds,
        nonneg=nonneg,
        **settings,
    )
    binds = 0
    for d, w, t, nn, res in zip(datafits, weights, thresholds, nonneg, got):
        want = staged_fista(d, penalty_weights=w, threshold=t, nonneg=nn, **settings)
        if nn is not None:
            assert np.all(res.coef.numpy()[nn.numpy()] >= 0)
            free = staged_fista(d, penalty_weights=w, threshold=t, **settings)
            binds += bool(np.any(free.coef.numpy()[nn.numpy()] < 0))
        np.testing.assert_array_equal(res.support, want.support)
        np.testing.assert_allclose(res.coef.numpy(), want.coef.numpy(), atol=1e-12)
        assert res.cost == pytest.approx(want.cost, rel=1e-10, abs=1e-15)
        assert len(res.stages) == len(want.stages)
        for a, b in zip(res.stages, want.stages):
            np.testing.assert_array_equal(a.support, b.support)
            np.testing.assert_allclose(a.coef, b.coef, atol=1e-8)
    assert len({len(r.support) for r in got}) > 1
    assert binds == 2  # measured: the constraint binds in problems 2 and 4


def test_staged_fista_batch_keeps_a_small_unpenalised_feature():
    """The hard threshold spares unpenalised (known) features, as staged_fista."""
    rng = np.random.default_rng(5)
    p, n = 8, 400
    A = rng.standard_normal((n, p))
    y = A[:, :3] @ np.array([0.01, 1.0, -0.8]) + 0.001 * rng.standard_normal(n)
    datafits = [gram_problem(A, y)] * 2
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


def test_the_refit_keeps_non_negative_coefficients_in_a_batch_too():
    """Least squares wants w = (1, -0.5); with w1 >= 0 the refit is the
    non-negative least squares (0.75, 0), alone and in lockstep; a start below zero
    there is projected (the stage's own solution stays feasible)."""
    a = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=torch.float64)
    y = a @ torch.tensor([1.0, -0.5], dtype=torch.float64)
    datafit = GramQuadratic(a.T @ a, a.T @ y, float(y @ y))
    nonneg = torch.tensor([False, True])
    settings = dict(lam=1e-6, threshold=0.0)
    both = staged_fista_batch([datafit, datafit], nonneg=[nonneg] * 2, **settings)
    alone = staged_fista(datafit, nonneg=nonneg, **settings)
    for res in [alone, *both]:
        # measured: exact (the NNLS of projected FISTA to KKT 1e-12 ends on it)
        np.testing.assert_allclose(res.coef.numpy(), [0.75, 0.0], rtol=0, atol=1e-9)
    start = torch.tensor([1.0, -0.5], dtype=torch.float64)
    raw = staged_fista(datafit, nonneg=nonneg, w0=start, debias=False, **settings)
    assert float(raw.coef[1]) == 0.0 and raw.stages[0].coef[1] == 0.0


def test_batches_group_what_can_run_in_lockstep():
    """CPU float64 Gram quadratics of one size go in lockstep (with ``shared``: all
    of them on it); a problem alone, another kind or dtype are solved alone."""
    rng = np.random.default_rng(3)

    def quad(p, cls=GramQuadratic, dtype=torch.float64):
        g, b, c = random_gram(rng, 100, p)
        return cls(torch.tensor(g, dtype=dtype), torch.tensor(b, dtype=dtype), c)

    def kinds(datafits, shared=None):
        return [
            (members, kind.__name__, share is not None)
            for members, kind, share in staged_module._batches(datafits, shared)
        ]

    mixed = [quad(4), quad(4), quad(5), quad(4, dtype=torch.float32), quad(5),
             quad(4, TensorGram), quad(6)]  # fmt: skip
    assert kinds(mixed) == [
        ([0, 1], "Lockstep", False),
        ([2, 4], "Lockstep", False),
        ([3, 5, 6], "Alone", False),
    ]
    assert kinds(mixed[:1]) == [([0], "Alone", False)]
    shared = (np.eye(6), [np.arange(4), np.arange(4)])
    assert kinds(mixed[:2], shared) == [([0, 1], "Lockstep", True)]
    # and every problem gets its own schedule's outcome, in order
    settings = dict(lam=1e-2, tol=1e-6, solver_tol=1e-9)
    got = staged_fista_batch(mixed, **settings)
    for d, res in zip(mixed, got):
        want = staged_fista(d, **settings)
        np.testing.assert_array_equal(res.support, want.support)
        assert res.coef.dtype == d.rhs.dtype
        # measured: equal; the batched refit may differ from a lone one by up to
        # 1e-10 relative on ill-conditioned supports (these are not)
        np.testing.assert_allclose(res.coef, want.coef, rtol=1e-10, atol=1e-12)


def test_verbose_prints_every_stage(capsys):
    rng = np.random.default_rng(4)
    g, b, c = random_gram(rng, 100, 5)
    datafit = GramQuadratic(torch.tensor(g), torch.tensor(b), c)
    res = staged_fista(datafit, lam=1e-1, tol=0.0, max_stages=2, verbose=1)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(res.stages) == 2
    assert lines[0].startswith("[lagsindy] stage 1: lam=0.1 ")
    assert f"terms={res.stages[1].support.size}" in lines[1]
    staged_fista_batch([datafit, datafit], lam=1e-1, tol=0.0, max_stages=1, verbose=1)
    lines = capsys.readouterr().out.splitlines()
    assert [ln[:32] for ln in lines] == [
        "[lagsindy] problem 1, stage 1: l",
        "[lagsindy] problem 2, stage 1: l",
    ]
