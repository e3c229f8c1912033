"""The hard threshold also judged per equation (issue #41, the light-link collapse).

Problems whose rows stack several coordinates' Euler-Lagrange equations carry each
column's share of norm per equation (``GramQuadratic.equation_shares``, from
:class:`~lagsindy.formulation.scaling.BalancedGram`); a term that contributes at
least ``equation_threshold`` times the dominant term of some equation is kept
whatever the global ``threshold`` says.
"""

import numpy as np
import pytest
import torch

from lagsindy.formulation.scaling import BalancedGram
from lagsindy.solvers import GramQuadratic, StagedFISTA, staged_fista
from lagsindy.solvers.staged import staged_fista_batch

# Two equations: features 0 and 1 act in the first (a heavy, driven coordinate),
# features 2 and 3 in the second (a link 30-500 times lighter).
SHARES = torch.tensor([[1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0]], dtype=torch.float64)


def _problem(w_true, shares=SHARES, target=(1.0, 0.0)):
    """Orthonormal columns: the least-squares solution is ``w_true`` exactly."""
    w = torch.tensor(w_true, dtype=torch.float64)
    gram = torch.eye(len(w_true), dtype=torch.float64)
    return GramQuadratic(
        gram,
        w.clone(),
        float(w @ w),
        shares,
        None if shares is None else torch.tensor(target, dtype=torch.float64),
    )


def _support(datafit, **kw):
    res = staged_fista(datafit, lam=1e-6, threshold=0.05, **kw)
    return res.support.tolist(), res.coef.numpy()


def test_a_light_links_dominant_terms_are_kept():
    w_true = [1.0, 0.1, 0.03, 0.002]
    # 0.03 is the light equation's largest; 0.002 is 6.7 % of it (< 0.25); 0.1 is
    # 10 % of the heavy one's (< 0.25) but kept by the global rule (> 0.05)
    support, coef = _support(_problem(w_true))
    assert support == [0, 1, 2]
    # judged in its own equation with the threshold itself: kept too
    support, coef = _support(_problem(w_true), equation_threshold=0.05)
    assert support == [0, 1, 2, 3]
    np.testing.assert_allclose(coef, w_true, rtol=1e-9)  # debiased: exact
    # the paper's rule drops both (3 % and 0.2 % of the largest, 1.0)
    support, _ = _support(_problem(w_true), equation_threshold=None)
    assert support == [0, 1]


@pytest.mark.parametrize("small, kept", [(0.00740, False), (0.00760, True)])
def test_the_equation_threshold_boundary(small, kept):
    """0.25 of the light equation's largest term (0.03) is 0.0075."""
    support, _ = _support(_problem([1.0, 0.5, 0.03, small]))
    assert (3 in support) is kept


def test_one_equation_is_the_global_rule():
    w_true = [1.0, 0.5, 0.03, 0.002]
    one = torch.ones((1, 4), dtype=torch.float64)
    a = staged_fista(_problem(w_true, one, (1.0,)), lam=1e-3)
    b = staged_fista(_problem(w_true, None), lam=1e-3, equation_threshold=None)
    assert a.support.tolist() == b.support.tolist() == [0, 1]
    np.testing.assert_array_equal(a.coef.numpy(), b.coef.numpy())


def test_a_term_in_both_equations_counts_where_it_matters_most():
    """Feature 2 is small in the heavy equation (share 0.6: 0.6 * 0.02 = 1.2 % of
    1.0) but the largest in the light one (0.8 * 0.02 = 0.016 against 0.01)."""
    shares = torch.tensor([[1.0, 0.0, 0.6], [0.0, 1.0, 0.8]], dtype=torch.float64)
    support, _ = _support(_problem([1.0, 0.01, 0.02], shares))
    assert support == [0, 1, 2]
    support, _ = _support(_problem([1.0, 0.01, 0.02], shares), equation_threshold=None)
    assert support == [0]


def test_the_reference_sets_each_equations_scale():
    """Case III: the fixed term (reference 1) acts in the light equation with share
    0.1, so that equation's scale is at least 0.1; a term of 0.004 there is 4 %."""
    support, _ = _support(
        _problem([1.0, 0.5, 0.004, 0.02], target=(0.995, 0.1)),
        reference=1.0,
        equation_threshold=0.05,
    )
    assert support == [0, 1, 3]
    support, _ = _support(
        _problem([1.0, 0.5, 0.006, 0.02], target=(0.995, 0.1)),
        reference=1.0,
        equation_threshold=0.05,
    )
    assert support == [0, 1, 2, 3]


def test_batched_problems_use_their_own_shares():
    a, b = _problem([1.0, 0.5, 0.03, 0.002]), _problem([1.0, 0.5, 0.03, 0.001])
    res = staged_fista_batch([a, b], lam=1e-6, threshold=0.05, equation_threshold=0.05)
    # 0.002 / 0.03 = 6.7 % is kept, 0.001 / 0.03 = 3.3 % is not
    assert [r.support.tolist() for r in res] == [[0, 1, 2, 3], [0, 1, 2]]


def test_restricting_a_datafit_keeps_its_shares():
    d = _problem([1.0, 0.5, 0.03, 0.002]).restrict([1, 3])
    np.testing.assert_array_equal(d.equation_shares.numpy(), [[1, 0], [0, 1]])
    np.testing.assert_array_equal(d.target_shares.numpy(), [1, 0])


def test_balanced_gram_shares_are_each_columns_norm_per_equation():
    rng = np.random.default_rng(0)
    cols = rng.normal(size=(2, 50, 3)) * np.array([1.0, 0.01])[:, None, None]
    cols[1, :, 0] = 0.0  # feature 0 acts in the first equation only
    y = rng.normal(size=(2, 50, 1))
    a = np.concatenate([cols, y], axis=2)
    gram = torch.tensor(np.einsum("isp,isq->ipq", a, a))
    bal = BalancedGram(gram, 50, 3)
    shares = bal.equation_shares.numpy()
    w = 1.0 / bal.row_scale.numpy() ** 2
    per_eq = np.einsum("isp,isp->ip", a, a) * w[:, None]
    np.testing.assert_allclose(shares, np.sqrt(per_eq / per_eq.sum(0)), rtol=1e-12)
    np.testing.assert_allclose((shares**2).sum(0), 1.0, rtol=1e-12)
    assert shares[1, 0] == 0.0
    datafit, _ = bal.problem([0, 2], 3)
    np.testing.assert_array_equal(datafit.equation_shares.numpy(), shares[:, [0, 2]])
    # without normalization the threshold compares coefficients: no shares
    datafit, _ = BalancedGram(gram, 50, 3, normalize=False).problem([0, 2], 3)
    assert datafit.equation_shares is None


def test_the_setting_reaches_the_schedule():
    assert StagedFISTA().equation_threshold == 0.25
    settings = StagedFISTA(equation_threshold=None)
    assert settings.schedule()["equation_threshold"] is None
    with pytest.raises(ValueError, match="equation_threshold"):
        StagedFISTA(equation_threshold=2.0).validate()
