"""lagsindy.formulation.scaling: balancing, the fixed-term residual bounds, and the
problems cut from one balanced block."""

import numpy as np
import torch

from lagsindy.formulation.scaling import BalancedGram, balance_rows


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
