"""Rollout (output-error) refinement of fitted coefficients: lagsindy.refine."""

import copy
import dataclasses
import warnings

import numpy as np
import pytest
import sympy as sp
from sklearn.exceptions import ConvergenceWarning

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy, refine
from lagsindy.refine import (
    INTEGRATOR_MARGIN,
    LARGE_CHANGE,
    NEGLIGIBLE_ERROR,
    integration_too_coarse,
    large_changes,
)
from lagsindy.systems import cart_pendulum, make_dataset, planar_chain, single_pendulum


def _with_coef(est, factors, dissipation=None):
    """A copy of ``est`` whose coefficients are multiplied by ``factors``."""
    fitted = dataclasses.replace(
        est.fitted_,
        coef=est.coef_ * factors,
        dissipation_coef=(
            est.dissipation_coef_ if dissipation is None else np.asarray(dissipation)
        ),
    )
    out = copy.deepcopy(est)
    out._publish(fitted)
    return out


def _perturbation(n, size=0.03):
    # deterministic, mixed signs, every term moved
    return 1 + size * np.cos(1.0 + 2.3 * np.arange(n))


@pytest.fixture(scope="module")
def double_chain():
    system = planar_chain(2, masses=[1.0, 0.6], lengths=[1.0, 0.7])
    d = make_dataset(
        system, n_trajectories=6, duration=2.0, excitation=None, random_state=3
    )
    lib = CandidateLibrary.chain(system.coordinates)
    est = LagrangianSINDy(lib, random_state=0).fit(d.X_clean, groups=d.groups)
    return system, d, lib, est


@pytest.mark.parametrize("initial_states", ["fit", "data"])
def test_passive_refinement_returns_to_the_exact_model(double_chain, initial_states):
    _, d, _, est = double_chain
    support = est.coef_ != 0
    assert support.sum() == 5
    factors = np.where(support, _perturbation(est.coef_.size), 1.0)
    start = _with_coef(est, factors)
    out = refine(
        start, d.X_clean, groups=d.groups, t=d.t, initial_states=initial_states
    )
    rep = out.refinement_
    # the held term keeps its coefficient; the others return to the exact fit
    held = list(est.term_names_).index(rep.held)
    assert rep.held == est.fixed_term_
    assert out.coef_[held] == start.coef_[held]
    ratios = out.coef_[support] / out.coef_[held]
    rel = np.abs(ratios / (est.coef_[support] / est.coef_[held]) - 1)
    assert rel.max() < 3e-4  # measured 6.0e-5 (RK4 at the sample step)
    assert rep.rmse_after < 2e-5 * rep.rmse_before  # measured 3.6e-6 x
    assert rep.converged and rep.n_windows == 6 * 2  # 200 samples: starts 0 and 50
    np.testing.assert_array_equal(start.coef_, est.coef_ * factors)  # not changed


def test_forced_refinement_uses_the_forces_between_samples():
    system = cart_pendulum()
    d = make_dataset(
        system,
        n_trajectories=4,
        duration=2.0,
        excitation="sincos",
        amplitude=3.0,
        random_state=1,
    )
    lib = CandidateLibrary.chain(system.coordinates, angles=["theta"])
    est = LagrangianSINDy(lib, random_state=0).fit(d.X_clean, d.tau, groups=d.groups)
    support = est.coef_ != 0
    start = _with_coef(est, np.where(support, _perturbation(est.coef_.size), 1.0))
    out = refine(start, d.X_clean, d.tau, groups=d.groups, t=d.t)
    assert out.refinement_.held is None  # forces fix the scale: every term moves
    rel = np.abs(out.coef_[support] / est.coef_[support] - 1)
    assert rel.max() < 3e-4  # measured 7.1e-5


def _pendulum_with(system, kind):
    """Passive pendulum data of ``system`` and a fit with one ``kind`` force term."""
    d = make_dataset(
        system, n_trajectories=4, duration=2.0, excitation=None, random_state=2
    )
    lib = CandidateLibrary.polynomial(["theta"], angles=["theta"], degree=2)
    est = LagrangianSINDy(
        lib, dissipation=DissipationLibrary([kind]), fixed_term="theta_dot**2"
    ).fit(d.X_clean, groups=d.groups)
    assert [t.name for t in est.dissipation_terms_] == [f"{kind}(theta)"]
    return d, est


def test_dissipation_stays_non_negative():
    # data that gain energy: the best viscous coefficient would be negative
    system = single_pendulum().with_damping(viscous={"theta": -0.05})
    d, est = _pendulum_with(system, "viscous")
    start = _with_coef(est, 1.0, dissipation=[0.2])  # a damped start
    with pytest.warns(UserWarning, match=r"viscous\(theta\) -(99|100) %"):
        out = refine(start, d.X_clean, groups=d.groups, t=d.t)
    # at the bound, approached from inside (measured 0.00032); unbounded: negative
    assert 0 <= out.dissipation_coef_[0] < 0.002
    assert out.refinement_.rmse_after < 0.5 * out.refinement_.rmse_before


def test_dissipation_keeps_the_sign_of_the_kinetic_energy():
    # the model of test_dissipation_stays_non_negative times -1 (passive data fix
    # the Lagrangian up to a factor): the viscous coefficient is now bounded at 0
    # from above, not refused or pushed to the other side
    system = single_pendulum().with_damping(viscous={"theta": -0.05})
    d, est = _pendulum_with(system, "viscous")
    start = _with_coef(est, -1.0, dissipation=[-0.2])
    with pytest.warns(UserWarning, match=r"viscous\(theta\) -(99|100) %"):
        out = refine(start, d.X_clean, groups=d.groups, t=d.t)
    assert out.coef_[list(est.term_names_).index("theta_dot**2")] == -1.0  # held
    assert -0.002 < out.dissipation_coef_[0] <= 0  # measured -0.00032
    assert out.refinement_.rmse_after < 0.5 * out.refinement_.rmse_before


@pytest.fixture(scope="module")
def biased_pendulum():
    # a constant torque -0.3 on a conservative pendulum: a signed "bias" force
    system = single_pendulum().with_damping()
    system.forces = [system.forces[0] - sp.Float(0.3)]
    return _pendulum_with(system, "bias")


@pytest.mark.parametrize("factor", [0.5, -0.5])
def test_bias_forces_are_signed(biased_pendulum, factor):
    # a bias is a constant force, not a dissipation: refine neither crashes on a
    # negative start (a diagnosed double pendulum's bias did) nor stops it at zero
    d, est = biased_pendulum
    b = est.dissipation_coef_[0]  # measured -0.59997 (scale of theta_dot**2 = 1)
    start = _with_coef(est, 1.0, dissipation=[factor * b])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the bias moves by 100 %
        out = refine(start, d.X_clean, groups=d.groups, t=d.t)
    assert abs(out.dissipation_coef_[0] / b - 1) < 5e-4  # measured 5.5e-5
    assert out.refinement_.rmse_after < 1e-5 * out.refinement_.rmse_before


def test_negative_dissipative_start_is_refused():
    d, est = _pendulum_with(single_pendulum(), "viscous")
    start = _with_coef(est, 1.0, dissipation=[-0.1])
    with pytest.raises(ValueError, match=r"viscous\(theta\).*feed energy in"):
        refine(start, d.X_clean, groups=d.groups, t=d.t)


def test_windows_never_span_a_gap(double_chain):
    _, d, _, est = double_chain
    # cut 30 samples out of the middle of the first trajectory: its 200 samples
    # become 85 + 85 (too short for one window each), the other five keep two
    keep = np.ones(len(d.t), dtype=bool)
    first = np.flatnonzero(d.groups == d.groups[0])
    keep[first[85:115]] = False
    out = refine(est, d.X_clean[keep], groups=d.groups[keep], t=d.t[keep])
    assert out.refinement_.n_windows == 5 * 2
    assert out.refinement_.rmse_after < 1e-6  # measured 3.0e-7
    # without the times, the positions' jump against the velocities shows the gap
    # (without that check two windows spanned it: RMSE 0.157)
    blind = refine(est, d.X_clean[keep], groups=d.groups[keep])
    assert blind.refinement_.n_windows == 5 * 2


def test_errors_and_warnings(double_chain):
    _, d, _, est = double_chain
    with pytest.raises(ValueError, match="horizon"):
        refine(est, d.X_clean, groups=d.groups, horizon=1)
    with pytest.raises(ValueError, match="no trajectory has 301 samples"):
        refine(est, d.X_clean, groups=d.groups, horizon=300)
    with pytest.raises(ValueError, match="passive"):
        refine(est, d.X_clean, np.zeros((len(d.t), 2)), groups=d.groups)
    with pytest.raises(ValueError, match="weights"):
        refine(est, d.X_clean, groups=d.groups, weights=[1.0, -1.0])
    with pytest.raises(ValueError, match="weights"):
        refine(est, d.X_clean, groups=d.groups, weights="unit")
    start = _with_coef(est, np.where(est.coef_ != 0, _perturbation(est.coef_.size), 1))
    with pytest.warns(ConvergenceWarning, match="raise max_iter"):
        out = refine(start, d.X_clean, groups=d.groups, max_iter=1)
    assert not out.refinement_.converged
    assert "rollout refinement over 12 windows of 100 samples" in str(out.refinement_)


def test_forced_model_needs_its_forces():
    system = single_pendulum()
    d = make_dataset(
        system, n_trajectories=3, duration=2.0, excitation="paper", random_state=0
    )
    lib = CandidateLibrary.polynomial(["theta"], angles=["theta"], degree=2)
    est = LagrangianSINDy(lib).fit(d.X_clean, d.tau, groups=d.groups)
    with pytest.raises(ValueError, match="pass the forces"):
        refine(est, d.X_clean, groups=d.groups)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # exact model: no warning
        out = refine(est, d.X_clean, d.tau, groups=d.groups, t=d.t, weights="std")
    assert out.refinement_.rmse_after <= out.refinement_.rmse_before


def test_fitted_initial_states_keep_noisy_starts_out_of_the_coefficients():
    # positions with noise 1e-2, derivatives by the default P-spline: the estimated
    # velocities at the windows' starts are off (most at the trajectories' ends);
    # held there, they pull the coefficients away from the truth
    system = cart_pendulum()
    d = make_dataset(
        system,
        n_trajectories=10,
        duration=4.0,
        excitation="sincos",
        noise=1e-2,
        protocol="sensor",
        random_state=1,
    )
    lib = CandidateLibrary.chain(system.coordinates, angles=["theta"])
    truth = lib.decompose(system.lagrangian)[0]
    est = LagrangianSINDy(lib, random_state=0).fit(d.X, d.tau, groups=d.groups)
    k = truth != 0
    assert np.array_equal(est.coef_ != 0, k)

    def error(e):
        return np.abs(e.coef_[k] / truth[k] - 1).max()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fitted = refine(est, d.X, d.tau, groups=d.groups, t=d.t)
        held = refine(est, d.X, d.tau, groups=d.groups, t=d.t, initial_states="data")
    assert fitted.refinement_.converged  # in 4 integrations
    assert error(fitted) < 0.7 * error(est)  # measured 0.63 % from 1.22 %
    assert error(held) > 5 * error(est)  # measured 14.4 %


# ------------------------------------------------------- thresholds at their boundary
@pytest.mark.parametrize(
    "change, large",
    [
        (LARGE_CHANGE, False),
        (LARGE_CHANGE * (1 + 1e-9), True),
        (-LARGE_CHANGE * (1 + 1e-9), True),
        (0.3, True),  # between the threshold and twice it
        (-0.3, True),
    ],
)
def test_changes_count_as_large_just_above_the_threshold(change, large):
    got = large_changes({"a": change, "b": 0.0, "c": -0.5 * LARGE_CHANGE})
    assert got == ({"a": change} if large else {})


def test_a_coefficient_moved_by_a_quarter_is_reported(double_chain):
    """A real refinement: one coefficient started 30 % high returns to the exact
    model (a change of 1/1.3 - 1 = -23 %, between the threshold and twice it)."""
    _, d, _, est = double_chain
    kept = np.flatnonzero(est.coef_)
    moved = next(k for k in kept if est.term_names_[k] != est.fixed_term_)
    factors = np.ones(est.coef_.size)
    factors[moved] = 1.3
    with pytest.warns(UserWarning, match="more than 20%") as caught:
        out = refine(_with_coef(est, factors), d.X_clean, groups=d.groups, t=d.t)
    name = str(est.term_names_[moved])
    assert out.refinement_.changes[name] == pytest.approx(1 / 1.3 - 1, abs=1e-3)
    large = [str(w.message) for w in caught if "more than 20%" in str(w.message)]
    assert len(large) == 1 and f"{name} -23 %" in large[0]


@pytest.mark.parametrize(
    "error, rmse, spread, coarse",
    [
        (1.0, INTEGRATOR_MARGIN, 1.0, False),  # exactly the margin below
        (1.0, INTEGRATOR_MARGIN * (1 - 1e-9), 1.0, True),
        (1.0, 0.5 * INTEGRATOR_MARGIN, 1.0, True),
        # an error at the negligible level of the spread is never reported
        (NEGLIGIBLE_ERROR, 1e-9, 1.0, False),
        (NEGLIGIBLE_ERROR * (1 + 1e-9), 1e-9, 1.0, True),
    ],
)
def test_integration_is_too_coarse_just_beyond_its_margins(error, rmse, spread, coarse):
    assert integration_too_coarse(error, rmse, spread) is coarse
