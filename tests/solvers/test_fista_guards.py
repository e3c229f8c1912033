"""FISTA's guards: a step above 2/L is reduced, a diverging run is halved and then
stopped with a clear error (issue #8, item 2)."""

import numpy as np
import pytest
import torch

from lagsindy.solvers import L1, GramQuadratic, fista


def test_fista_reduces_a_step_above_two_over_lipschitz():
    rng = np.random.default_rng(0)
    a = torch.as_tensor(rng.standard_normal((50, 5)))
    y = a @ torch.tensor([1.0, 0.0, -2.0, 0.0, 0.5], dtype=torch.float64)
    df = GramQuadratic(a.T @ a / 50, a.T @ y / 50, float(y @ y) / 50)
    res = fista(df, L1(1e-3), step=1e50, tol=1e-10, max_iter=5000)
    lip = df.lipschitz()
    assert res.converged and res.step * lip <= 2.0 and res.step_reductions >= 160
    ref = fista(df, L1(1e-3), tol=1e-10, max_iter=5000)
    # measured: equal; the runs stop at the KKT tolerance 1e-10
    np.testing.assert_allclose(res.coef, ref.coef, atol=1e-10)


class _LyingGram(GramQuadratic):
    """Claims a Lipschitz constant far too small, so the 2/L guard cannot help."""

    def lipschitz(self):
        return 1e-12 * super().lipschitz()


def test_fista_divergence_guard_gives_a_clear_error():
    rng = np.random.default_rng(1)
    a = torch.as_tensor(rng.standard_normal((40, 4)))
    y = a.sum(dim=1)
    df = _LyingGram(a.T @ a / 40, a.T @ y / 40, float(y @ y) / 40)
    with pytest.raises(FloatingPointError, match=r"diverged.*halved 3 times.*alpha"):
        fista(df, L1(0.0), step=1e6, max_step_reductions=3, max_iter=10_000)
    # with enough halvings the guard alone recovers
    res = fista(df, L1(0.0), step=1e6, tol=1e-9, max_iter=20_000)
    assert res.converged and res.step_reductions > 0
    np.testing.assert_allclose(res.coef, np.ones(4), atol=1e-11)  # measured 1.5e-12
