"""lagsindy.formulation.forms: which formulation a fit uses (the default weak form on
time-ordered rows, the strong form with a warning on shuffled ones) and what counts
as time-ordered."""

import numpy as np
import pytest
import torch

from lagsindy import LagrangianSINDy
from lagsindy.formulation import WeakForm
from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum


def test_default_is_the_weak_form_on_one_ordered_record(pendulum):
    """Without groups the rows are split where a trajectory ends (a noise-free record
    whose trajectories end near where the next begins included)."""
    est = LagrangianSINDy(single_pendulum().paper_library()).fit(
        pendulum.X, pendulum.tau
    )
    assert est.formulation_ == "weak"
    c = dict(zip(est.term_names_, est.coef_))
    # measured 6.1e-5 and 4.5e-8 relative errors; the old 0.1 split floor merged
    # trajectories (2 %)
    assert c["theta_dot**2"] == pytest.approx(0.5, rel=1e-4)
    assert c["cos(theta)"] == pytest.approx(9.81, rel=1e-4)


def test_shuffled_rows_fall_back_to_the_strong_form_and_say_so(pendulum):
    rows = np.random.default_rng(0).permutation(len(pendulum.X))
    X, tau = pendulum.X[rows], pendulum.tau[rows]
    lib = single_pendulum().paper_library()
    with pytest.warns(UserWarning, match="fell back to the strong form") as seen:
        est = LagrangianSINDy(lib).fit(X, tau)
    assert est.formulation_ == "strong"
    assert seen[0].filename == __file__  # points at the caller's fit
    with pytest.raises(ValueError, match="time-ordered|positive sampling interval"):
        LagrangianSINDy(lib, formulation=WeakForm(dt=0.01)).fit(X, tau)


@pytest.mark.parametrize("sigma", [0.1, 0.2])
def test_very_noisy_trajectories_still_count_as_time_ordered(sigma):
    """Lag-1 steps drown in noise of 0.1 (their correlation with the velocities was
    0.15, so the weak form refused and the default fell back to the biased strong
    form); the longer lags see the motion. Shuffled rows stay near 0."""
    from lagsindy.formulation.weak import check_time_order, trajectory_segments

    data = make_dataset(
        cart_pendulum(),
        n_trajectories=20,
        excitation="paper",
        noise=sigma,
        protocol="shared",
        random_state=0,
    )
    X = torch.tensor(data.X)
    segs = trajectory_segments(X, 2, data.groups)
    # measured 0.979 (0.1) and 0.924 (0.2), at lag 32
    assert check_time_order(X, 2, segs) > 0.9
    shuffled = X[torch.randperm(X.shape[0], generator=torch.Generator().manual_seed(0))]
    # measured below 0.03
    assert (
        check_time_order(shuffled, 2, trajectory_segments(shuffled, 2, data.groups))
        < 0.1
    )
    est = LagrangianSINDy(cart_pendulum().paper_library()).fit(
        data.X, data.tau, groups=data.groups
    )
    assert est.formulation_ == "weak"
