"""The weak (integral) formulation and its errors-in-variables noise correction."""

import warnings

import numpy as np
import pytest
import torch

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy.euler_lagrange import (
    EulerLagrangeOperator,
    bump_function,
    estimate_noise_covariance,
    estimate_sampling_interval,
    trajectory_segments,
)
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    make_dataset,
    single_pendulum,
)


def _rel_err(est, truth):
    return np.linalg.norm(est.coef_ - truth) / np.linalg.norm(truth)


def test_weak_columns_equal_integrated_strong_columns():
    """int psi * EL(phi) dt: by parts (weak) equals the direct integral of Theta."""
    data = make_dataset(
        cart_pendulum(), n_trajectories=2, excitation="sincos", random_state=0
    )
    lib = cart_pendulum().paper_library()
    op = EulerLagrangeOperator(lib.coordinates_, lib.terms_)
    X = torch.tensor(data.X_clean)
    seg = [torch.arange(0, 500)]
    window, stride, dt = 61, 15, 0.01
    weak, n_w = op.weak_gram(X, None, seg, window=window, stride=stride, dt=dt)
    theta = op.columns(X[:500])  # strong columns (exact accelerations)
    psi, _ = bump_function(window, dt)
    direct = torch.stack(
        [
            (psi[:, None, None] * theta[s : s + window]).sum(0) * dt
            for s in range(0, 500 - window + 1, stride)
        ]
    )
    assert direct.shape[0] == n_w
    ref = torch.einsum("wip,wiq->ipq", direct, direct)
    np.testing.assert_allclose(
        weak.numpy(), ref.numpy(), rtol=2e-4, atol=1e-6 * float(ref.abs().max())
    )


def test_noise_covariance_estimate():
    rng = np.random.default_rng(0)
    t = np.arange(2000) * 0.01
    clean = np.stack([np.sin(t), np.cos(2 * t), 2 * np.cos(t), -4 * np.sin(2 * t)], 1)
    independent = clean + rng.normal(size=clean.shape) * np.array(
        [0.01, 0.02, 0.05, 0.1]
    )
    cov = estimate_noise_covariance(
        torch.tensor(independent), [torch.arange(2000)], 2
    ).numpy()
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), [0.01, 0.02, 0.05, 0.1], rtol=0.1)
    assert abs(cov[0, 3]) < 0.1 * np.sqrt(cov[0, 0] * cov[3, 3])
    shared = clean + 0.05 * rng.normal(size=(2000, 1))
    cov = estimate_noise_covariance(
        torch.tensor(shared), [torch.arange(2000)], 2
    ).numpy()
    corr = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    assert corr.min() > 0.99  # one shared sample per step: fully correlated


def test_noise_correction_removes_expected_bias():
    """Averaged over noise draws, the corrected Gram matches the clean one.

    The kinetic entry's bias is first order in the noise variance and must vanish;
    entries with sines and cosines keep a small second-order shrinkage
    (E cos(q + e) = exp(-sigma^2 / 2) cos q, 2 % at sigma = 0.2), which the first-order
    correction does not model.
    """
    data = make_dataset(
        single_pendulum(), n_trajectories=4, excitation="paper", random_state=1
    )
    lib = CandidateLibrary.from_terms(["theta"], ["theta_dot**2", "cos(theta)"])
    op = EulerLagrangeOperator(lib.coordinates_, lib.terms_)
    segs = [torch.arange(i * 500, (i + 1) * 500) for i in range(4)]
    kw = dict(window=41, stride=10, dt=0.01)
    clean = op.weak_gram(torch.tensor(data.X_clean), None, segs, **kw)[0][0].numpy()
    sigma, draws = 0.2, 40
    cov = torch.eye(2, dtype=torch.float64) * sigma**2
    rng = np.random.default_rng(2)
    raw, corrected = [], []
    for _ in range(draws):
        noisy = torch.tensor(data.X_clean + sigma * rng.normal(size=data.X_clean.shape))
        raw.append(op.weak_gram(noisy, None, segs, **kw)[0][0].numpy())
        corrected.append(
            op.weak_gram(noisy, None, segs, noise_cov=cov, **kw)[0][0].numpy()
        )
    raw, corrected = np.array(raw), np.array(corrected)
    se = raw.std(axis=0) / np.sqrt(draws)
    assert raw.mean(0)[0, 0] - clean[0, 0] > 5 * se[0, 0]  # attenuation bias
    assert abs(corrected.mean(0)[0, 0] - clean[0, 0]) < 3 * se[0, 0]  # removed
    np.testing.assert_allclose(corrected.mean(0), clean, rtol=0.05, atol=3 * se.max())


def test_noise_part_equals_its_definition_by_brute_force():
    """The noise Gram is sum_w sum_s J_ws^T Lambda J_ws, J_ws = d cols_w / d x_s.

    The reference differentiates each window's columns with respect to each sample
    by reverse-mode autograd of a direct sum over the window (no per-sample weights,
    no factorization), for two coordinates, a non-diagonal Lambda, batched and
    general Lagrangian terms, and force terms.
    """
    import sympy as sp

    names = ["x", "theta"]
    x, t = sp.symbols(names, real=True)
    xd, td = sp.symbols(["x_dot", "theta_dot"], real=True)
    terms = [xd**2, xd * td * sp.cos(t), sp.exp(-(x**2)) * td**2, sp.cos(t)]
    forces = [[-sp.tanh(5 * xd), 0], [td - xd, xd - td]]
    op = EulerLagrangeOperator(names, terms, forces=forces)
    rng = np.random.default_rng(4)
    X = torch.tensor(rng.normal(size=(47, 6)))
    segs = [torch.arange(0, 30), torch.arange(30, 47)]
    window, stride, dt = 9, 4, 0.05
    cov = torch.tensor(
        [
            [0.3, 0.1, 0.0, 0.05],
            [0.1, 0.2, 0.0, 0.0],
            [0.0, 0.0, 0.4, 0.1],
            [0.05, 0.0, 0.1, 0.5],
        ]
    )
    _, noise, _ = op.weak_gram(
        X,
        None,
        segs,
        window=window,
        stride=stride,
        dt=dt,
        noise_cov=cov.double(),
        return_noise=True,
    )
    psi, dpsi = bump_function(window, dt)
    d, p = 2, len(terms) + len(forces)
    q_s, qd_s = [x, t], [xd, td]
    # integrands per coordinate i and column k: a = dphi/dqd_i (zero for forces),
    # b = dphi/dq_i (Q_k,i for forces); each window's column is -dt sum(dpsi a + psi b)
    a_exprs = [
        [sp.diff(f, qd_s[i]) for f in terms] + [0] * len(forces) for i in range(d)
    ]
    b_exprs = [
        [sp.diff(f, q_s[i]) for f in terms] + [fo[i] for fo in forces] for i in range(d)
    ]
    fa = sp.lambdify(q_s + qd_s, a_exprs, modules="numpy")
    fb = sp.lambdify(q_s + qd_s, b_exprs, modules="numpy")
    eps = 1e-6  # central differences of the integrands, per sample
    want = np.zeros((d, p, p))
    covn = cov.numpy()
    for seg in segs:
        rows = X[seg, :4].numpy()
        n = len(rows)
        da = np.zeros((n, d, p, 4))
        db = np.zeros((n, d, p, 4))
        for b in range(4):
            up, down = rows.copy(), rows.copy()
            up[:, b] += eps
            down[:, b] -= eps
            for out, f in ((da, fa), (db, fb)):
                hi = np.array(
                    [np.broadcast_to(np.asarray(f(*r), float), (d, p)) for r in up]
                )
                lo = np.array(
                    [np.broadcast_to(np.asarray(f(*r), float), (d, p)) for r in down]
                )
                out[..., b] = (hi - lo) / (2 * eps)
        for start in range(0, n - window + 1, stride):
            for j in range(window):
                s = start + j
                jac = -dt * (
                    dpsi[j].item() * da[s] + psi[j].item() * db[s]
                )  # (d, p, 4)
                want += np.einsum("ikx,xy,ily->ikl", jac, covn, jac)
    # measured: 2.6e-11 of the largest entry (the central differences' error)
    np.testing.assert_allclose(
        noise[:, :p, :p].numpy(), want, rtol=1e-9, atol=1e-9 * np.abs(want).max()
    )


def test_weak_form_is_exact_on_noise_free_data(cart_active):
    lib = cart_pendulum().paper_library()
    est = LagrangianSINDy(lib, formulation="weak", dt=0.01).fit(
        cart_active.X, cart_active.tau, groups=cart_active.groups
    )
    truth = cart_pendulum().true_coefficients(lib)
    np.testing.assert_array_equal(est.coef_ != 0, truth != 0)
    assert _rel_err(est, truth) < 1e-6
    # noise-free data: the estimated noise is negligible and nothing is subtracted
    assert est.dt_ == 0.01 and est.noise_cov_ is None


def test_weak_form_with_noise_correction_beats_strong_form():
    system = cart_pendulum()
    lib = system.paper_library()
    truth = system.true_coefficients(lib)
    data = make_dataset(
        system,
        n_trajectories=20,
        excitation="sincos",
        noise=0.05,
        protocol="paper",
        random_state=3,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        strong = LagrangianSINDy(lib, formulation="strong").fit(data.X, data.tau)
        weak_raw = LagrangianSINDy(
            lib, formulation="weak", dt=0.01, noise_cov=None
        ).fit(data.X, data.tau, groups=data.groups)
        weak = LagrangianSINDy(lib, formulation="weak", dt=0.01).fit(
            data.X, data.tau, groups=data.groups
        )
    # measured: strong 0.56, weak without correction 0.08, weak corrected 0.010
    assert _rel_err(strong, truth) > 0.3  # attenuation of the paper's strong form
    assert _rel_err(weak_raw, truth) > 0.04
    assert _rel_err(weak, truth) < 0.02
    np.testing.assert_array_equal(weak.coef_ != 0, truth != 0)


def test_overestimated_noise_covariance_is_projected_not_propagated():
    """Noise correction for 10x the real noise: the nearest PSD Gram keeps the truth.

    Subtracting too much leaves the corrected Gram indefinite; the fit uses its
    nearest positive semi-definite matrix.
    Measured (noise 0.01, noise_cov for 0.1): smallest eigenvalue of the corrected
    Gram -2e-5; relative coefficient error 0.0015 with the projection, 0.013
    without (the indefinite direction inflates both coefficients by 1.2 %).
    """
    system = single_pendulum()
    lib = system.paper_library()
    truth = system.true_coefficients(lib)
    data = make_dataset(
        system,
        n_trajectories=10,
        excitation="paper",
        noise=0.01,
        protocol="paper",
        random_state=3,
    )
    est = LagrangianSINDy(
        lib, formulation="weak", dt=0.01, noise_cov=np.eye(2) * 0.1**2
    ).fit(data.X, data.tau, groups=data.groups)
    np.testing.assert_array_equal(est.coef_ != 0, truth != 0)
    assert _rel_err(est, truth) < 0.004


def test_weak_form_case_III_passive():
    system = double_pendulum()
    lib = system.paper_library()
    data = make_dataset(
        system,
        n_trajectories=20,
        excitation=None,
        noise=0.05,
        protocol="paper",
        random_state=4,
    )
    est = LagrangianSINDy(
        lib,
        formulation="weak",
        dt=0.01,
        fixed_term=system.fixed_term,
        unpenalized=system.prior_terms,
    ).fit(data.X, groups=data.groups)
    truth = system.true_coefficients(lib)
    truth = truth / truth[lib.index(system.fixed_term)]
    np.testing.assert_array_equal(est.coef_ != 0, truth != 0)
    assert _rel_err(est, truth) < 0.05


def test_segments_and_dt_without_groups():
    data = make_dataset(
        single_pendulum(),
        n_trajectories=5,
        duration=2.0,
        excitation="paper",
        noise=0.01,
        protocol="paper",
        random_state=5,
    )
    X = torch.tensor(data.X)
    dt = estimate_sampling_interval(X, 1, [torch.arange(len(X))])
    assert dt == pytest.approx(0.01, rel=0.02)
    segs = trajectory_segments(X, 1, None, dt=0.01)
    assert [int(s[0]) for s in segs] == [0, 200, 400, 600, 800]
    est = LagrangianSINDy(
        single_pendulum().paper_library(), formulation="weak", window=41
    )
    est.fit(data.X, data.tau)  # no groups, no dt: both inferred
    assert est.dt_ == pytest.approx(0.01, rel=0.02)
    assert set(est.term_names_[est.support_]) == {"theta_dot**2", "cos(theta)"}


def test_weak_form_errors(single_active):
    lib = single_pendulum().paper_library()
    with pytest.raises(ValueError, match="window"):
        LagrangianSINDy(lib, formulation="weak", dt=0.01, window=1001).fit(
            single_active.X, single_active.tau, groups=single_active.groups
        )
    with pytest.raises(ValueError, match="noise_cov must have shape"):
        LagrangianSINDy(lib, formulation="weak", dt=0.01, noise_cov=np.eye(3)).fit(
            single_active.X, single_active.tau, groups=single_active.groups
        )
    with pytest.raises(ValueError, match="groups"):
        LagrangianSINDy(lib, formulation="weak", dt=0.01).fit(
            single_active.X, single_active.tau, groups=single_active.groups[:10]
        )
    with pytest.raises(ValueError, match="weak"):
        LagrangianSINDy(lib, formulation="weak", case="acceleration", dt=0.01).fit(
            single_active.X
        )


# ----------------------------------------------------------------- window="auto"
def test_window_ladder_doubles_while_the_trajectories_allow():
    from lagsindy.formulation import window_ladder

    assert window_ladder([500] * 20, 2, 39) == [81, 161, 321]  # 641 > 500
    assert window_ladder([2000] * 5, 2, 39) == [81, 161, 321, 641]  # at most 4
    # 161 would drop the 150-sample trajectories (half the samples): never tried
    assert window_ladder([150] * 10 + [300] * 5, 2, 10) == [81]
    assert window_ladder([60] * 3, 1, 2) == []
    # enough windows for the terms: 2 trajectories of 500 give 2 windows of 321
    assert window_ladder([500] * 2, 1, 4) == [81, 161]


def _assert_same_to_rounding(a, b):
    """Equal to 1e-12 of the matrix's largest entry: entries that are zero but for
    rounding (1e-21 against 0.14 in the noise part) differ between CPUs and orders of
    summation, so an entrywise relative tolerance alone would fail on some
    machines."""
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())


def test_weak_grams_of_several_windows_equal_one_window_each():
    """One evaluation of the integrands serves every window: the statistics of each
    equal a separate weak_gram call, including the noise part and a trajectory too
    short for the longer window (its rows then carry no weight)."""
    data = make_dataset(
        cart_pendulum(),
        n_trajectories=3,
        excitation="sincos",
        noise=0.01,
        random_state=3,
    )
    lib = cart_pendulum().paper_library()
    op = EulerLagrangeOperator(lib.coordinates_, lib.terms_)
    X = torch.tensor(data.X)
    tau = torch.tensor(data.tau)
    segs = [torch.arange(0, 500), torch.arange(500, 620), torch.arange(1000, 1500)]
    cov = torch.diag(torch.tensor([1e-4, 2e-4, 3e-4, 1e-3], dtype=torch.float64))
    kw = dict(dt=0.01, noise_cov=cov, noise_rows=700, return_noise=True)
    by_window = {61: segs, 161: [segs[0], segs[2]]}
    both = op.weak_grams(X, tau, by_window, strides={61: 15, 161: 40}, **kw)
    for window, stride in ((61, 15), (161, 40)):
        alone = op.weak_gram(
            X, tau, by_window[window], window=window, stride=stride, **kw
        )
        if window == 161:  # the noise subsample differs (fewer rows): compare raw
            alone = (alone[0], None, alone[2])
        for a, b in zip(both[window], alone):
            if b is not None:
                _assert_same_to_rounding(np.asarray(a), np.asarray(b))
    # the noise part of the longer window, with every row sampled, against alone
    kw["noise_rows"] = 10**6
    both = op.weak_grams(X, tau, by_window, strides={61: 15, 161: 40}, **kw)
    alone = op.weak_gram(X, tau, by_window[161], window=161, stride=40, **kw)
    _assert_same_to_rounding(both[161][1].numpy(), alone[1].numpy())
    assert float(alone[1].abs().max()) > 0


@pytest.fixture(scope="module")
def cart_positions_only():
    """Cart-pendulum, positions with noise 1e-2 rad, derivatives by the P-spline."""
    system = cart_pendulum()
    data = make_dataset(
        system,
        n_trajectories=20,
        duration=5,
        excitation="sincos",
        noise=0.01,
        protocol="sensor",
        random_state=0,
    )
    return system, data


def test_window_auto_lengthens_the_window_for_smoothed_derivatives(
    cart_positions_only,
):
    """The P-spline's derivative errors are smooth: at 81 samples the coefficients
    are 6.9 % off (benchmarks/results/defaults.md); 161 and 321 agree within 0.3 %,
    so "auto" keeps 161 (measured error 0.78 %)."""
    system, data = cart_positions_only
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the ladder settles: no warning
        est = LagrangianSINDy(system.paper_library()).fit(
            data.X, data.tau, groups=data.groups
        )
    truth = system.true_coefficients(est.library_)
    assert est.window_ == 161
    assert np.array_equal(est.coef_ != 0, truth != 0)
    assert _rel_err(est, truth) < 0.012  # measured 0.0078
    short = LagrangianSINDy(system.paper_library(), window=81).fit(
        data.X, data.tau, groups=data.groups
    )
    assert short.window_ == 81 and _rel_err(short, truth) > 0.05  # measured 0.069


def test_white_velocities_tell_measured_from_smoothed(cart_positions_only):
    """Velocities with white noise (measured) are left to the noise correction;
    P-spline derivatives and noise-free velocities have none (2e-6 of their spread),
    so window="auto" checks longer windows for them."""
    from lagsindy.formulation.weak import white_velocities

    system, smoothed = cart_positions_only

    def white(data):
        X = torch.tensor(data.X)
        return white_velocities(X, trajectory_segments(X, 2, data.groups), 2)

    assert not white(smoothed)
    for noise, expected in ((0.0, False), (1e-3, True)):
        data = make_dataset(
            system,
            n_trajectories=3,
            excitation="sincos",
            noise=noise,
            protocol="paper",
            random_state=1,
        )
        assert white(data) is expected
    est = LagrangianSINDy(system.paper_library()).fit(
        data.X, data.tau, groups=data.groups
    )
    assert est.window_ == 81


def test_window_auto_keeps_81_when_the_next_window_agrees(cart_active):
    est = LagrangianSINDy(cart_pendulum().paper_library()).fit(
        cart_active.X, cart_active.tau, groups=cart_active.groups
    )
    assert est.formulation_ == "weak" and est.window_ == 81


def test_window_auto_warns_when_no_window_settles(cart_positions_only, monkeypatch):
    """With a threshold no pair meets, the first window is kept and a
    WindowWarning names the windows and how far each step moved."""
    import lagsindy.formulation.weak as weak
    from lagsindy import WindowWarning

    monkeypatch.setattr(weak, "WINDOW_CHANGE", 1e-12)
    system, data = cart_positions_only
    with pytest.warns(WindowWarning, match=r"windows of 81, 161, 321 samples") as rec:
        est = LagrangianSINDy(system.paper_library()).fit(
            data.X, data.tau, groups=data.groups
        )
    assert est.window_ == 81
    moves = str(rec[0].message).split("(")[1].split(")")[0].split(", ")
    first, second = (float(m.rstrip("%")) for m in moves)
    assert 5.5 < first < 7 and second < 0.5  # measured 6.1 %, 0.3 %


def test_weak_r2_scores_what_the_weak_form_fits(cart_positions_only):
    """On held-out trajectories with P-spline derivatives, the pointwise R^2 of the
    forces counts the noise of the estimated accelerations against the right model;
    the R^2 over the test windows does not, and ranks it above the strong form's
    biased 10-term model."""
    import torch

    system, data = cart_positions_only
    train = data.groups < 15
    test = ~train
    weak = LagrangianSINDy(system.paper_library()).fit(
        data.X[train], data.tau[train], groups=data.groups[train]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        strong = LagrangianSINDy(system.paper_library(), formulation="strong").fit(
            data.X[train], data.tau[train]
        )
    Xt = torch.as_tensor(data.X[test])
    r2_weak = weak.fitted_.weak_r2(Xt, data.tau[test], data.groups[test])
    # the strong model scored the same way (windows of 81 samples)
    r2_strong = strong.fitted_.weak_r2(Xt, data.tau[test], data.groups[test])
    pointwise = weak.score(data.X[test], data.tau[test])
    assert r2_weak > 0.99  # measured 0.9966
    assert r2_strong < 0.6  # measured 0.489
    assert pointwise < 0  # measured -3.17


def _cart_weak_case(n_trajectories, random_state, noise=0.01):
    """The cart-pendulum's paper-library operator, its rows and inputs as tensors,
    and a noise covariance for [q, qd]."""
    data = make_dataset(
        cart_pendulum(), n_trajectories=n_trajectories, excitation="sincos",
        noise=noise, random_state=random_state,
    )  # fmt: skip
    lib = cart_pendulum().paper_library()
    op = EulerLagrangeOperator(lib.coordinates_, lib.terms_)
    cov = torch.diag(torch.tensor([1e-4, 2e-4, 3e-4, 1e-3], dtype=torch.float64))
    return op, torch.tensor(data.X), torch.tensor(data.tau), cov


def test_reuse_weak_columns_gives_the_statistics_of_a_fresh_call(reused_grams):
    """Inside reuse_weak_columns a second call on the same samples with other forces
    takes the features' part from the first and equals a fresh call (noise part
    included); other samples, or leaving the block, compute afresh."""
    import lagsindy.formulation.operator as operator_module

    op, X, tau, cov = _cart_weak_case(3, 4)
    shifted = torch.roll(tau, 3, dims=0) * 1.5
    segs = [torch.arange(0, 500), torch.arange(500, 1000), torch.arange(1000, 1500)]
    kw = dict(
        strides={61: 15, 121: 30}, dt=0.01, noise_cov=cov, noise_rows=700,
        return_noise=True,
    )  # fmt: skip
    by_window = {61: segs, 121: segs[:2]}
    reused = reused_grams
    fresh = op.weak_grams(X, shifted, by_window, **kw)
    with operator_module.reuse_weak_columns():
        first = op.weak_grams(X, tau, by_window, **kw)
        assert not reused
        again = op.weak_grams(X, shifted, by_window, **kw)
        assert len(reused) == 1
        op.weak_grams(X * 1.01, shifted, by_window, **kw)  # other samples: afresh
        assert len(reused) == 1
    op.weak_grams(X, shifted, by_window, **kw)  # outside the block: afresh
    assert len(reused) == 1
    for window in by_window:
        for a, b in zip(again[window], fresh[window]):
            a, b = np.asarray(a), np.asarray(b)
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
        # the forces' row did change: the comparison can fail
        assert not torch.allclose(first[window][0][:, -1], fresh[window][0][:, -1])


def test_reuse_weak_columns_serves_a_subset_of_the_kept_features(reused_grams):
    """A call whose features are among a kept call's (in another order, forces
    included, with or without a generalized force) takes their block: it equals a
    fresh call to rounding; a feature the kept call lacks means a fresh call."""
    import sympy as sp

    import lagsindy.formulation.operator as operator_module
    from lagsindy._expr import symbols_for
    from lagsindy.dissipation import make_term

    _, X, tau, cov = _cart_weak_case(3, 5)
    terms = list(cart_pendulum().paper_library().terms_)
    coords = ["x", "theta"]
    forces = [
        make_term(kind, c, coords).forces
        for kind, c in (("viscous", "x"), ("coulomb", "theta"), ("drag", "x"))
    ]
    union = EulerLagrangeOperator(coords, terms, forces=forces)
    pick = [7, 0, 3, 12]  # a few terms, not in the library's order
    sub = EulerLagrangeOperator(coords, [terms[k] for k in pick], forces=forces[1:2])
    q_s, qd_s, _ = symbols_for(coords)
    wider = EulerLagrangeOperator(coords, terms[:3] + [sp.exp(q_s[0]) * qd_s[1] ** 2])
    segs = [torch.arange(0, 500), torch.arange(500, 1000), torch.arange(1000, 1500)]
    kw = dict(strides={61: 15}, dt=0.01, noise_cov=cov, noise_rows=700)
    kw["return_noise"] = True
    reused = reused_grams
    fresh = {y: sub.weak_grams(X, y, {61: segs}, **kw)[61] for y in (None, tau)}
    with operator_module.reuse_weak_columns():
        union.weak_grams(X, None, {61: segs}, **kw)  # kept, without a force
        got = {y: sub.weak_grams(X, y, {61: segs}, **kw)[61] for y in (None, tau)}
        assert len(reused) == 2
        wider.weak_grams(X, tau, {61: segs}, **kw)  # a term not kept: afresh
        assert len(reused) == 2
    for y in (None, tau):
        for a, b in zip(got[y][:2], fresh[y][:2]):  # Gram, noise part
            a, b = a.numpy(), b.numpy()
            assert a.shape == b.shape == (2, 5 + (y is not None), 5 + (y is not None))
            # measured: the Gram equal, the noise part to 1.5e-18 of its largest
            # entry (a gather of the kept block; rounding may differ on other BLAS)
            np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14 * np.abs(b).max())
        assert got[y][2] == fresh[y][2]  # windows
    assert float(fresh[tau][1].abs().max()) > 0  # the noise part is there to compare


def test_reuse_weak_columns_keeps_its_own_copy():
    """A caller changing the matrices a kept call returned does not change what a
    later call gathers."""
    import lagsindy.formulation.operator as operator_module

    op, X, tau, _ = _cart_weak_case(2, 6, noise=0.0)
    segs = [torch.arange(0, 500), torch.arange(500, 1000)]
    kw = dict(strides={61: 15}, dt=0.01, return_noise=True)
    with operator_module.reuse_weak_columns():
        first = op.weak_grams(X, tau, {61: segs}, **kw)[61]
        want = first[0].clone()
        first[0].mul_(2.0)  # the caller's own business
        again = op.weak_grams(X, tau, {61: segs}, **kw)[61]
    # the force row is summed again (rounding); the doubled matrix would be 2x off
    np.testing.assert_allclose(again[0].numpy(), want.numpy(), rtol=1e-12)


@pytest.mark.parametrize("chunk", [1, 600])
def test_weak_integrands_by_chunks_equal_one_block(monkeypatch, chunk):
    """The integrands evaluated by groups of whole trajectories (one each, or a few)
    give the Gram statistics of one evaluation on all rows, noise part included,
    with trajectories of several lengths."""
    import lagsindy.formulation.operator as operator_module

    op, X, tau, cov = _cart_weak_case(4, 7)
    segs = [torch.arange(0, 500), torch.arange(500, 800), torch.arange(1000, 1500)]
    segs.append(torch.arange(1500, 1700))
    kw = dict(
        strides={61: 15, 161: 40}, dt=0.01, noise_cov=cov, return_noise=True
    )  # fmt: skip
    by_window = {61: segs, 161: segs[:3]}
    monkeypatch.setattr(operator_module, "WEAK_CHUNK", 1 << 40)  # one block
    whole = op.weak_grams(X, tau, by_window, **kw)
    monkeypatch.setattr(operator_module, "WEAK_CHUNK", chunk * 316)  # ~chunk rows
    parts = op.weak_grams(X, tau, by_window, **kw)
    order = torch.cat(segs)
    groups, owner = op._integrand_chunks(
        X[order, :2], X[order, 2:4], order, tau, None, [len(s) for s in segs]
    )
    # one trajectory per group, or 500 + 300 and 500 + 200 rows
    assert [g[0] for g in groups] == ([0, 500, 800, 1300] if chunk == 1 else [0, 800])
    assert owner == ([0, 1, 2, 3] if chunk == 1 else [0, 0, 1, 1])
    for window in by_window:
        for a, b in zip(parts[window][:2], whole[window][:2]):
            a, b = a.numpy(), b.numpy()
            # measured: equal (the same kernels row by row, summed in the same order)
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13 * np.abs(b).max())
        assert parts[window][2] == whole[window][2]
