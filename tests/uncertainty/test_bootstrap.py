"""lagsindy.uncertainty.bootstrap: the resamples' fast path against full refits, the
report, block resampling, and the agreement checks at their thresholds."""

import warnings

import numpy as np
import pytest
from _helpers import SMALL_PENDULUM_TERMS, small_pendulum_library
from sklearn.base import clone

from lagsindy import (
    BootstrapReport,
    DissipationLibrary,
    LagrangianSINDy,
    bootstrap,
    pipeline,
)
from lagsindy._validation import validate_state
from lagsindy.formulation import WeakForm, make_formulation
from lagsindy.formulation.forms import group_rows
from lagsindy.systems import make_dataset, single_pendulum
from lagsindy.uncertainty import _resampling as R
from lagsindy.uncertainty.bootstrap import (
    _BATCH_RTOL,
    _SEAM_RTOL,
    FEW_GROUPS,
    reproduces,
    warn_few_groups,
)


def _group_stats(full, Xa, tau_a, groups):
    """The per-group statistics of ``full`` and the data as tensors."""
    Xt, tau_t = R.tensors(full, Xa, tau_a)
    return R.group_statistics(full, Xt, tau_t, groups), Xt


def _fast(full, stats, Xt, m, start=None):
    return R.fast_resample(pipeline.setup_of(full), stats, m, Xt, {}, start)


def _compare_paths(est, X, tau, groups, n_check=3):
    """Max difference between the fast path and full refits on a few resamples."""
    full = clone(est).fit(X, tau, groups=groups)
    Xa, tau_a, _ = validate_state(
        full, X, reset=False, y=tau, coordinates=full.coordinates_
    )
    stats, Xt = _group_stats(full, Xa, tau_a, groups)
    weak = full.formulation == "weak"
    extra = {}
    if weak:
        form = WeakForm(window=full.window_, noise_cov=full.noise_cov_)
        extra = {"formulation": form}
    base = clone(est).set_params(library=clone(full.library_), **extra)
    rows_of = group_rows(groups)
    rng = np.random.default_rng(1)
    worst = 0.0
    n_groups = len(rows_of)
    for _ in range(n_check):
        m = rng.multinomial(n_groups, np.full(n_groups, 1.0 / n_groups))
        a = _fast(full, stats, Xt, m, full.stages_[0].coef)
        b = R.refit_resample(base, Xa, tau_a, rows_of, m, weak)
        assert np.array_equal(a != 0, b != 0)
        worst = max(worst, np.abs(a - b).max() / np.abs(b).max())
    return worst


@pytest.mark.parametrize("formulation", ["strong", "weak"])
def test_fast_path_matches_full_refits_case_i(noisy_pendulum, formulation):
    d = noisy_pendulum
    est = LagrangianSINDy(single_pendulum().paper_library(), formulation=formulation)
    # measured: 2.5e-13 (strong), 9.5e-15 (weak), relative to the largest
    # coefficient
    assert _compare_paths(est, d.X, d.tau, d.groups) < 1e-12


def test_resamples_estimate_their_own_sampling_interval():
    d = make_dataset(
        single_pendulum(),
        n_trajectories=10,
        duration=2.0,
        excitation="paper",
        noise=0.02,
        protocol="paper",
        random_state=5,
    )
    est = LagrangianSINDy(small_pendulum_library(), formulation="weak")
    full = clone(est).fit(d.X, d.tau, groups=d.groups)
    Xa, tau_a, _ = validate_state(
        full, d.X, reset=False, y=d.tau, coordinates=full.coordinates_
    )
    stats, Xt = _group_stats(full, Xa, tau_a, d.groups)
    assert stats.sampling_interval(np.ones(10)) == full.dt_
    m = np.array([0, 1, 0, 0, 2, 2, 1, 1, 3, 0])
    take = np.repeat(np.arange(10), m)
    rows = np.concatenate([np.flatnonzero(d.groups == g) for g in take])
    labels = np.repeat(np.arange(m.sum()), 200)
    # the resamples hold the noise covariance and the window fixed, not dt
    fixed = {
        "formulation": make_formulation(
            est.formulation, noise_cov=full.noise_cov_, window=full.window_
        )
    }
    refit = clone(est).set_params(**fixed).fit(d.X[rows], d.tau[rows], groups=labels)
    # measured: 1.2 % below the full data's estimate on this resample
    assert stats.sampling_interval(m) == pytest.approx(refit.dt_, rel=1e-12)
    assert abs(refit.dt_ / full.dt_ - 1) > 5e-3
    # the Gram matrix interpolated at that dt is the one built there: same fit
    # (measured: 1e-16 relative; 1e-13 leaves room for another BLAS's rounding)
    coef = _fast(full, stats, Xt, m)
    np.testing.assert_allclose(coef, refit.fitted_.all_coef(), rtol=1e-13)


@pytest.mark.parametrize("formulation", ["strong", "weak"])
def test_batched_resamples_equal_one_at_a_time(noisy_pendulum, formulation):
    d = noisy_pendulum
    est = LagrangianSINDy(single_pendulum().paper_library(), formulation=formulation)
    full = clone(est).fit(d.X, d.tau, groups=d.groups)
    Xa, tau_a, _ = validate_state(
        full, d.X, reset=False, y=d.tau, coordinates=full.coordinates_
    )
    stats, Xt = _group_stats(full, Xa, tau_a, d.groups)
    rng = np.random.default_rng(7)
    mults = rng.multinomial(8, np.full(8, 1 / 8), size=25)
    start = full.stages_[0].coef
    setup = pipeline.setup_of(full)
    assert R.batch_supported(setup, Xt.dtype)
    batched = R.batched_resamples(setup, stats, mults, start)
    assert all(b is not None for b in batched)
    for m, b in zip(mults, batched):
        a = _fast(full, stats, Xt, m, start)
        assert np.array_equal(a != 0, b != 0)
        # measured: 8.5e-14 (strong), 7.9e-11 (weak) relative to the largest
        # coefficient (the two solves stop their iterations apart)
        assert np.abs(a - b).max() <= 4e-10 * np.abs(a).max()


def test_fast_path_matches_full_refits_case_iii():
    d = make_dataset(
        single_pendulum(),
        n_trajectories=6,
        duration=2.0,
        excitation=None,
        random_state=1,
    )
    est = LagrangianSINDy(
        single_pendulum().paper_library(),
        fixed_term="theta_dot**2",
        formulation="strong",
    )
    assert R.fast_path_supported(clone(est).fit(d.X))
    # measured: 1.4e-15 relative to the largest coefficient
    assert _compare_paths(est, d.X, None, d.groups) < 1e-13


def test_report_table_and_determinism(noisy_pendulum):
    d = noisy_pendulum
    est = LagrangianSINDy(small_pendulum_library(), formulation="weak")
    rep = bootstrap(
        est,
        d.X,
        d.tau,
        groups=d.groups,
        n_resamples=10,
        method="percentile",
        random_state=3,
    )
    assert isinstance(rep, BootstrapReport) and rep.fast_path
    frame = rep.to_frame()
    assert list(frame.columns) == [
        "term",
        "kind",
        "coefficient",
        "inclusion",
        "low",
        "high",
    ]
    assert list(frame.term) == SMALL_PENDULUM_TERMS
    assert "inclusion" in str(rep) and "cos(theta)" in str(rep)
    # the full fit's coefficients are the estimator's own
    ref = clone(est).fit(d.X, d.tau, groups=d.groups)
    np.testing.assert_array_equal(frame.coefficient, ref.coef_)
    again = bootstrap(
        est,
        d.X,
        d.tau,
        groups=d.groups,
        n_resamples=10,
        method="percentile",
        random_state=3,
        n_jobs=2,
    )
    np.testing.assert_array_equal(rep.samples, again.samples)
    np.testing.assert_array_equal(rep.low, again.low)


def test_block_bootstrap_of_one_record():
    d = make_dataset(
        single_pendulum(),
        n_trajectories=1,
        duration=8.0,
        excitation="paper",
        noise=0.01,
        protocol="sensor",
        random_state=2,
    )
    est = LagrangianSINDy(small_pendulum_library(), formulation="strong")
    rep = bootstrap(est, d.X, d.tau, n_resamples=20, random_state=0)
    assert rep.resampling == "blocks" and rep.n_groups == 20 and rep.fast_path
    frame = rep.to_frame().set_index("term")
    for term, value in [("cos(theta)", 9.81), ("theta_dot**2", 0.5)]:
        assert frame.loc[term, "inclusion"] == 1.0
        assert frame.loc[term, "low"] <= frame.loc[term, "coefficient"]
        assert frame.loc[term, "coefficient"] <= frame.loc[term, "high"]
    with pytest.raises(ValueError, match="n_blocks"):
        bootstrap(est, d.X, d.tau, n_blocks=1, n_resamples=5)
    # few trajectories are cut into blocks too
    few = bootstrap(
        est, d.X[:600], d.tau[:600], groups=np.repeat([0, 1], 300), n_resamples=5
    )
    assert few.resampling == "blocks" and few.n_groups == 20


def test_dissipation_rows_and_passive_normalization():
    system = single_pendulum().with_damping(viscous={"theta": 0.3})
    d = make_dataset(
        system, n_trajectories=6, duration=3.0, excitation=None, random_state=4
    )
    est = LagrangianSINDy(
        small_pendulum_library(),
        dissipation=DissipationLibrary(["viscous", "coulomb"]),
        fixed_term=None,  # the case III search: full refits, normalized like the fit
        formulation="strong",
    )
    rep = bootstrap(
        est, d.X, groups=d.groups, n_resamples=8, method="percentile", random_state=0
    )
    frame = rep.to_frame().set_index("term")
    assert not rep.fast_path
    assert list(frame.index[-2:]) == ["viscous(theta)", "coulomb(theta)"]
    assert list(frame.kind[-2:]) == ["dissipation", "dissipation"]
    fixed = rep.estimator.fixed_term_
    # every resample is put in the full fit's scale: the fixed term is exactly 1
    assert frame.loc[fixed, "low"] == frame.loc[fixed, "high"] == 1.0
    assert frame.loc["viscous(theta)", "inclusion"] == 1.0
    # viscous/kinetic = 0.3 / 0.5 = 0.6 in the theta_dot**2 = 1 scale
    ratio = (
        frame.loc["viscous(theta)", "coefficient"]
        / frame.loc["theta_dot**2", "coefficient"]
    )
    assert ratio == pytest.approx(0.6, rel=1e-12)  # noise-free: measured 5.6e-16


def test_bad_arguments(noisy_pendulum):
    d = noisy_pendulum
    est = LagrangianSINDy(small_pendulum_library(), formulation="strong")
    with pytest.raises(ValueError, match="method"):
        bootstrap(est, d.X, d.tau, groups=d.groups, method="normal")
    with pytest.raises(ValueError, match="n_resamples"):
        bootstrap(est, d.X, d.tau, groups=d.groups, n_resamples=1)
    with pytest.raises(ValueError, match="level"):
        bootstrap(est, d.X, d.tau, groups=d.groups, level=95)


# ------------------------------------------------------- thresholds at their boundary
@pytest.mark.parametrize("n_groups", [FEW_GROUPS - 1, FEW_GROUPS])
def test_fewer_than_five_groups_warn(n_groups):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warned = warn_few_groups(n_groups, "trajectories")
    assert warned is (n_groups < FEW_GROUPS)
    assert len(caught) == int(warned)
    if warned:
        assert f"only {n_groups} trajectories to resample" in str(caught[0].message)


def test_a_bootstrap_of_four_trajectories_warns():
    d = make_dataset(
        single_pendulum(), n_trajectories=2, duration=2.0, excitation="paper",
        random_state=0,
    )  # fmt: skip
    est = LagrangianSINDy(small_pendulum_library(), formulation="strong")
    with pytest.warns(UserWarning, match="only 4 blocks to resample"):
        rep = bootstrap(est, d.X, d.tau, groups=d.groups, n_blocks=4, n_resamples=4)
    assert rep.n_groups == 4


@pytest.mark.parametrize("rtol", [_SEAM_RTOL, _BATCH_RTOL])
def test_a_fast_path_is_trusted_up_to_its_tolerance(rtol):
    want = np.array([2.0, 0.0, -1.0])
    below, above = rtol * (1 - 1e-6), rtol * (1 + 1e-6)
    assert reproduces(want + [below, 0, 0], want, rtol, 1.0)
    assert reproduces(want - [0, 0, 2 * below], want, rtol, 2.0)
    assert not reproduces(want + [above, 0, 0], want, rtol, 1.0)
    assert not reproduces(want - [0, 0, 2 * above], want, rtol, 2.0)
    assert not reproduces(want + [0, 1e-300, 0], want, rtol, 1.0)  # other support
    assert not reproduces(None, want, rtol, 1.0)  # a failed solve


@pytest.fixture(scope="module")
def light_link_fit():
    """A double pendulum whose second link is 100 times lighter, strongly driven:
    the default fit solves again with every term judged within each coordinate's
    equation (``tests/model/test_checks.py``) and records that rule."""
    from lagsindy.systems import double_pendulum

    system = double_pendulum(m2=0.01)
    data = make_dataset(
        system, n_trajectories=10, duration=5, excitation="sincos", random_state=0
    )
    est = LagrangianSINDy(system.paper_library())
    with pytest.warns(UserWarning, match="judged within each coordinate's equation"):
        full = clone(est).fit(data.X, data.tau, groups=data.groups)
    return est, data, full


def test_refits_use_the_threshold_rule_the_fit_ended_with(light_link_fit):
    """The rule the fit ended with is recorded (``equation_threshold_``) and every
    refit of the configuration uses it: the fast path's setup, the full refits'
    configuration (``refit_config``), the diagnosis's refits. A fit that did not
    change its rule records nothing and refits itself."""
    from lagsindy.diagnostics.scoring import _fit_model
    from lagsindy.joint import refit_config, refit_setup
    from lagsindy.solvers import StagedFISTA

    est, data, full = light_link_fit
    rule = StagedFISTA().threshold  # judged in its own equation at the threshold
    assert full.equation_threshold_ == rule
    assert refit_setup(full).solver.equation_threshold == rule
    again = refit_config(full)
    assert again is not full and again.solver.equation_threshold == rule
    quiet = _fit_model(full, data.X, data.tau, data.groups, fit=False)
    assert quiet.solver.equation_threshold == rule
    # the refit with that rule is the fit itself, without a second judgement
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        refit = clone(again).fit(data.X, data.tau, groups=data.groups)
    assert not [w for w in caught if "judged within" in str(w.message)]
    np.testing.assert_allclose(
        refit.fitted_.all_coef(), full.fitted_.all_coef(), rtol=1e-10, atol=1e-12
    )

    plain = LagrangianSINDy(single_pendulum().paper_library(), formulation="strong")
    d = make_dataset(single_pendulum(), 3, 2.0, random_state=0)
    plain.fit(d.X, d.tau, groups=d.groups)
    assert not hasattr(plain, "equation_threshold_")
    assert refit_config(plain) is plain


def test_a_bootstrap_resamples_the_rule_the_fit_ended_with(light_link_fit):
    """Before: the resamples solved with the default rule, so the fast path did not
    reproduce the fit and every resample was a full refit deciding on its own
    whether to judge each equation (inclusion of the light link's gravity 0.60 in
    20 resamples). Now the fast path reproduces the fit and is used."""
    est, data, _ = light_link_fit
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        report = bootstrap(
            est,
            data.X,
            data.tau,
            groups=data.groups,
            n_resamples=2,
            method="percentile",
            random_state=0,
        )
    said = [str(w.message) for w in caught]
    assert not [m for m in said if "fast path" in m]
    assert report.fast_path
    assert report.estimator.equation_threshold_ == 0.05  # the default threshold
