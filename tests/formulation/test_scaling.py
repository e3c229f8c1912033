"""lagsindy.formulation.scaling: balancing, the fixed-term residual bounds, and the
problems cut from one balanced block."""

import warnings

import numpy as np
import pytest
import torch

from lagsindy.formulation.scaling import (
    NULL_RCOND,
    BalancedGram,
    balance_rows,
    fixed_term_bounds,
)


def _torch_balance(mean_sq, max_iter=2000):
    """The previous implementation: the balancing iterations on tensors."""
    rows = torch.ones(mean_sq.shape[0], dtype=mean_sq.dtype)
    for _ in range(max_iter):
        cols = torch.sqrt((mean_sq / rows[:, None] ** 2).mean(dim=0))
        active = cols > 0
        if not bool(active.any()):
            break
        ratio = mean_sq[:, active] / cols[active] ** 2
        new_rows = torch.sqrt(ratio.mean(dim=1))
        new_rows = torch.where(new_rows > 0, new_rows, torch.ones_like(new_rows))
        new_rows = new_rows / torch.exp(torch.log(new_rows).mean())
        if torch.allclose(new_rows, rows, rtol=1e-10, atol=0):
            return new_rows
        rows = new_rows
    return rows


def test_row_balance_on_numpy_equals_the_torch_iterations():
    rng = np.random.default_rng(0)
    for n_dof, p in ((2, 39), (3, 10), (1, 5)):
        mean_sq = rng.lognormal(sigma=3.0, size=(n_dof, p))
        mean_sq[0, 0] = 0.0  # a column zero in one coordinate
        if n_dof > 1:
            mean_sq[:, 1] = 0.0  # a column zero everywhere
        want = _torch_balance(torch.tensor(mean_sq)).numpy()
        # measured: 2.2e-16 relative at most
        np.testing.assert_allclose(balance_rows(mean_sq), want, rtol=1e-13)
    gram = torch.tensor(rng.normal(size=(2, 6, 6)))
    gram = gram @ gram.transpose(1, 2)
    for dtype in (torch.float64, torch.float32):
        balanced = BalancedGram(gram.to(dtype), 10, 5)
        assert balanced.row_scale.dtype == dtype


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


class _Block:
    """A stand-in for BalancedGram: ``block(free)`` gives a fixed scaled block."""

    def __init__(self, eigenvalues):
        rotation = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64))[0]
        values = torch.tensor(eigenvalues, dtype=torch.float64)
        self.gram = rotation @ torch.diag(values) @ rotation.T

    def block(self, free):
        return self.gram, None


@pytest.mark.parametrize(
    "small, allowed, warns",
    [
        (NULL_RCOND * 0.99, 0, True),  # a null combination in case I
        (NULL_RCOND * 1.01, 0, False),
        (NULL_RCOND * 0.99, 1, False),  # case III expects one (the Lagrangian)
    ],
)
def test_null_combinations_are_eigenvalues_below_the_relative_floor(
    small, allowed, warns
):
    """An eigenvalue of the scaled block at most NULL_RCOND times the largest is a
    null combination; more of them than ``allowed`` warn."""
    from lagsindy.formulation.scaling import (
        IdentifiabilityWarning,
        warn_if_not_identifiable,
    )

    block = _Block([small, 0.5, 1.0])
    names = ["a", "b", "c"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_if_not_identifiable(block, np.arange(3), names, allowed=allowed)
    assert [w.category for w in caught] == ([IdentifiabilityWarning] if warns else [])
    if warns:
        assert "1 combination(s) of candidate terms" in str(caught[0].message)


def test_equations_sharing_no_column_keep_finite_scales():
    """Two equations with no common column (a robot's joints with the URDF model
    held: each joint's rotor inertia and friction only on its own equation) have no
    common scale; averaging each row over every active column drove them apart by a
    constant factor per iteration (measured: 9e-89 and 1.1e88). Each row now
    averages over its own columns; a linked pattern keeps its scales."""
    from lagsindy.formulation.scaling import balance_rows

    apart = np.array(
        [[0.0, 1.1578, 0.0, 0.2421, 0.0, 0.0], [0.0, 0.0, 2.4909, 0.0, 0.2928, 0.1221]]
    )
    np.testing.assert_allclose(balance_rows(apart), [1.0, 1.0], rtol=1e-9)
    linked = apart.copy()
    linked[:, 0] = [0.5, 3.0]  # one column on both equations links them
    rows = balance_rows(linked)
    assert np.all(np.isfinite(rows)) and 1e-3 < rows[0] / rows[1] < 1e3
