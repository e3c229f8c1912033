"""Case III search: reused first starts and one-operator scoring change nothing."""


import numpy as np
import pytest
import torch

from lagsindy.cases.fixed import acceleration_r2s
from lagsindy.formulation.operator import forward_accelerations


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
    got = acceleration_r2s(p, coefs + [np.zeros(p.n_features)], Xs)
    want = [_r2_one_operator(p, c, Xs) for c in coefs]
    assert got[-1] == -np.inf
    # measured: equal to 1e-15; the supports differ, so a mix-up shows at 1e-2
    np.testing.assert_allclose(got[:-1], want, rtol=1e-12, atol=1e-12)
    assert len({round(g, 6) for g in got[:-1]}) > 1  # the models do score differently


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
