"""lagsindy.pipeline's seams: statistics summed per trajectory solve to the fit,
weighted totals are the statistics of repeated rows, a fitted state round-trips
through ``LagrangianSINDy.from_fitted``, and ``fitted_formulation`` keeps the
window a fit chose."""

import warnings

import numpy as np
import pytest
import torch
from _helpers import small_pendulum_library
from sklearn.base import clone

from lagsindy import CandidateLibrary, LagrangianSINDy, pipeline
from lagsindy.formulation.forms import StrongForm, TrajectoryStatistics, WeakForm
from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum


@pytest.fixture(scope="module")
def passive_noisy():
    return make_dataset(
        single_pendulum(), n_trajectories=8, duration=2.0, excitation=None,
        noise=0.01, protocol="sensor", random_state=3,
    )  # fmt: skip


def _fitted(data, formulation, passive):
    """A fit of the small pendulum library (case III with a fixed term when
    ``passive``) and the data as tensors."""
    est = LagrangianSINDy(
        small_pendulum_library(),
        formulation=formulation,
        fixed_term="theta_dot**2" if passive else None,
    )
    tau = None if passive else data.tau
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # what the fit says is tested elsewhere
        est.fit(data.X, tau, groups=data.groups)
    Xt = torch.as_tensor(np.asarray(data.X, dtype=float))
    tau_t = None if tau is None else torch.as_tensor(np.asarray(tau, dtype=float))
    return est, Xt, tau_t


def _trajectory_form(est):
    """The formulation of ``est``'s fit, for per-trajectory statistics."""
    if est.formulation_ == "strong":
        return StrongForm()
    return WeakForm(window=int(est.window_), dt=est.dt_, noise_cov=est.noise_cov_)


@pytest.mark.parametrize("formulation", ["strong", "weak"])
@pytest.mark.parametrize("passive", [False, True], ids=["case I", "case III"])
def test_solving_the_summed_trajectory_statistics_gives_the_fit(
    formulation, passive, noisy_pendulum, passive_noisy
):
    data = passive_noisy if passive else noisy_pendulum
    est, Xt, tau_t = _fitted(data, formulation, passive)
    assert est.formulation_ == formulation
    assert est.case_ == ("fixed" if passive else "forces")
    setup = pipeline.setup_of(est)
    operator = setup.operator(range(setup.n_features), Xt.device, Xt.dtype)
    per_trajectory = _trajectory_form(est).trajectory_statistics(
        operator, Xt, tau_t, data.groups
    )
    assert isinstance(per_trajectory, TrajectoryStatistics)
    assert len(per_trajectory) == len(np.unique(data.groups))
    stats = per_trajectory.total()
    # the Gram statistics of the fit itself (its formulation, its window)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        (build,) = pipeline.fit_statistics(
            pipeline.fitted_formulation(est), setup, Xt, tau_t, data.groups
        )
    own = build()
    assert stats.n_rows == own.n_rows and stats.window == own.window
    scale = own.gram.abs().max()
    # measured: 6.7e-16 and 4.1e-16 (strong), 0 (weak) of the largest entry
    torch.testing.assert_close(stats.gram, own.gram, rtol=0, atol=1e-13 * scale)
    solution = pipeline.solve(stats, setup, Xt, warn=False)
    want = est.fitted_.all_coef()
    np.testing.assert_array_equal(solution.coef != 0, want != 0)
    # measured: 3.2e-14 relative at most (the same solve of nearly the same sums)
    np.testing.assert_allclose(solution.coef, want, rtol=1e-12)
    fitted = pipeline.fitted_state(setup, stats, solution)
    np.testing.assert_allclose(fitted.coef, est.coef_, rtol=1e-12)
    assert fitted.formulation == formulation and fitted.window == est.fitted_.window


@pytest.mark.parametrize("formulation", ["strong", "weak"])
def test_weighted_totals_are_the_statistics_of_repeated_rows(
    formulation, noisy_pendulum
):
    data = noisy_pendulum
    est, Xt, tau_t = _fitted(data, formulation, passive=False)
    setup = pipeline.setup_of(est)
    operator = setup.operator(range(setup.n_features), Xt.device, Xt.dtype)
    form = _trajectory_form(est)
    if formulation == "weak":  # a noise covariance, so that there is a noise part
        form.set_params(noise_cov=np.diag([1e-4, 1e-3]))
    per_trajectory = form.trajectory_statistics(operator, Xt, tau_t, data.groups)
    weights = np.array([0, 2, 1, 3, 0, 1, 1, 2])  # a bootstrap resample of 8
    labels = np.unique(data.groups)
    rows = np.concatenate(
        [
            np.flatnonzero(data.groups == g)
            for g, m in zip(labels, weights)
            for _ in range(m)
        ]
    )
    groups = np.repeat(np.arange(weights.sum()), np.bincount(data.groups)[0])
    repeated = form.trajectory_statistics(operator, Xt[rows], tau_t[rows], groups)
    for corrected in (True, False):
        got = per_trajectory.total(weights, corrected=corrected)
        want = repeated.total(corrected=corrected)
        assert got.n_rows == want.n_rows
        assert (got.noise_cov is None) == (want.noise_cov is None)
        scale = want.gram.abs().max()
        # measured: 1.1e-16 of the largest entry at most (sums in another order)
        torch.testing.assert_close(got.gram, want.gram, rtol=0, atol=1e-13 * scale)
    # a fold: weights 0 and 1 take trajectories out
    fold = (weights > 0).astype(float)
    in_fold = np.isin(data.groups, labels[fold > 0])
    alone = form.trajectory_statistics(
        operator, Xt[in_fold], tau_t[in_fold], data.groups[in_fold]
    )
    torch.testing.assert_close(
        per_trajectory.total(fold).gram, alone.total().gram, rtol=1e-13, atol=0
    )
    if formulation == "weak":
        # the noise part is what the correction subtracts
        assert per_trajectory.noise is not None
        raw = per_trajectory.total(weights, corrected=False).gram
        noise = torch.einsum(
            "k,kipq->ipq",
            torch.as_tensor(weights, dtype=raw.dtype),
            per_trajectory.noise,
        )
        # measured: 1.8e-14 absolute, against raw entries up to 500 (cancellation)
        torch.testing.assert_close(
            raw - per_trajectory.total(weights).gram,
            noise,
            rtol=0,
            atol=1e-15 * raw.abs().max(),
        )


def test_from_fitted_round_trips_a_fitted_state(noisy_pendulum):
    data = noisy_pendulum
    est, _, _ = _fitted(data, "weak", passive=False)
    params = est.get_params(deep=False)
    again = LagrangianSINDy.from_fitted(est.fitted_, **params)
    assert again.fitted_ is est.fitted_
    assert again.get_params(deep=False).keys() == params.keys()
    for name in ("lam", "threshold", "formulation", "window", "fixed_term"):
        assert again.get_params()[name] == params[name]
    np.testing.assert_array_equal(again.coef_, est.coef_)
    np.testing.assert_array_equal(again.predict(data.X), est.predict(data.X))
    assert again.score(data.X, data.tau) == est.score(data.X, data.tau)
    assert again.n_features_in_ == est.n_features_in_ == 3
    assert again.window_ == est.window_ and again.formulation_ == "weak"
    # refitting the rebuilt estimator gives the original fit
    refit = clone(again).fit(data.X, data.tau, groups=data.groups)
    np.testing.assert_allclose(refit.coef_, est.coef_, rtol=1e-12)
    named = LagrangianSINDy.from_fitted(
        est.fitted_, feature_names_in=["theta", "theta_dot", "theta_ddot"]
    )
    assert list(named.feature_names_in_) == ["theta", "theta_dot", "theta_ddot"]


@pytest.fixture(scope="module")
def auto_window():
    """Cart-pendulum, positions with noise 1e-2, P-spline derivatives: the smoothing
    biases short windows, and window="auto" moves from 81 to 161 samples."""
    system = cart_pendulum()
    data = make_dataset(
        system, n_trajectories=10, duration=4.0, excitation="sincos", noise=1e-2,
        protocol="sensor", random_state=1,
    )  # fmt: skip
    library = CandidateLibrary.chain(system.coordinates, angles=["theta"])
    est = LagrangianSINDy(library, random_state=0).fit(
        data.X, data.tau, groups=data.groups
    )
    return data, est


def test_fitted_formulation_keeps_the_chosen_window(auto_window):
    data, est = auto_window
    assert est.formulation_ == "weak" and est.window_ == 161
    form = pipeline.fitted_formulation(est)
    assert isinstance(form, WeakForm) and form.window == 161
    assert form.noise_cov == "auto" and form.dt is None  # the rest as configured
    # a refit of the same configuration with it: the same window, the same model
    again = (
        clone(est)
        .set_params(formulation=form)
        .fit(data.X, data.tau, groups=data.groups)
    )
    assert again.window_ == 161
    np.testing.assert_allclose(again.coef_, est.coef_, rtol=1e-12)  # measured equal
    # an unfitted estimator: the formulation of its parameters
    unfitted = pipeline.fitted_formulation(clone(est))
    assert unfitted.window == "auto"
    strong = LagrangianSINDy(formulation="strong")
    assert isinstance(pipeline.fitted_formulation(strong), StrongForm)
