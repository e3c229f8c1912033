"""Sign constraints of the solvers: the L1 prox and the staged FISTA keep constrained
(dissipative) coefficients non-negative."""

import pytest
import torch

from lagsindy.solvers import L1, GramQuadratic, staged_fista


def test_l1_prox_projects_constrained_coefficients():
    pen = L1(0.1, None, torch.tensor([True, False]))
    out = pen.prox(torch.tensor([-1.0, -1.0], dtype=torch.float64), 1.0)
    assert out.tolist() == [0.0, -0.9]


def test_staged_fista_keeps_constrained_coefficients_non_negative():
    """Least squares wants w = (1, -0.5); with w_1 >= 0 the answer is (x, 0)."""
    a = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=torch.float64)
    y = a @ torch.tensor([1.0, -0.5], dtype=torch.float64)
    fit = GramQuadratic(a.T @ a, a.T @ y, float(y @ y))
    free = staged_fista(fit, lam=1e-6, threshold=0.0)
    # the debiasing refit is exact least squares: measured -0.5 to 5.6e-17
    assert float(free.coef[1]) == pytest.approx(-0.5, abs=1e-12)
    nonneg = torch.tensor([False, True])
    res = staged_fista(fit, lam=1e-6, threshold=0.0, nonneg=nonneg)
    assert float(res.coef[1]) == 0.0
    # NNLS: with w_1 = 0, w_0 = (y0 + y2) / 2 = 0.75
    assert float(res.coef[0]) == pytest.approx(0.75, abs=1e-12)  # measured exact
