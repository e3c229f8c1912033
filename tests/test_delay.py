"""Input delay (#13): estimate_delay, shift_input, lagsindy fit --delay."""

import re

import numpy as np
import pandas as pd
import pytest

from lagsindy import LagrangianSINDy, estimate_delay, shift_input
from lagsindy.cli import main
from lagsindy.systems import make_dataset, single_pendulum


@pytest.fixture(scope="module")
def delayed():
    """A forced pendulum recorded at 125 Hz whose input acts 30 ms (3.75 samples)
    after it is recorded: simulated at 1 kHz, the recorded input at row i is the
    force acting 30 ms later."""
    system = single_pendulum()
    fine = make_dataset(
        system, n_trajectories=4, duration=2.0, rate=1000.0, random_state=0
    )
    step, lag = 8, 30
    rows, recorded = [], []
    for g in np.unique(fine.groups):
        idx = np.flatnonzero(fine.groups == g)
        take = idx[: idx.size - lag : step]
        rows.append(take)
        recorded.append(fine.tau[take + lag])
    rows = np.concatenate(rows)
    return (
        system,
        fine.X[rows],
        np.concatenate(recorded),
        fine.t[rows],
        fine.groups[rows],
    )


def make(system):
    return LagrangianSINDy(system.paper_library(), formulation="strong")


def test_shift_input_interpolates_within_each_trajectory():
    t = np.r_[np.arange(5), np.arange(4)] * 0.01
    groups = np.repeat([0, 1], [5, 4])
    tau = np.c_[t * 100, -t * 100]
    out = shift_input(tau, t, 0.015, groups)
    np.testing.assert_allclose(out[:5, 0], [0, 0, 0.5, 1.5, 2.5])
    np.testing.assert_allclose(out[5:, 0], [0, 0, 0.5, 1.5])  # no leak from row 4
    np.testing.assert_allclose(out[:, 1], -out[:, 0])
    np.testing.assert_allclose(shift_input(tau[:, 0], t, 0.0, groups), tau[:, 0])
    with pytest.raises(ValueError, match="finite"):
        shift_input(tau, t, np.nan, groups)


def test_delay_is_estimated_and_removes_the_bias(delayed):
    system, X, tau, t, groups = delayed
    result = estimate_delay(
        make(system), X, tau, t, groups=groups, max_delay=0.048, n_splits=2
    )
    # measured 29.9952 ms +- 0.0061 ms (folds 29.9995 and 29.9872 ms; method="refit"
    # gives 35.8 ms +- 2.9 ms, see test_both_methods_on_a_dataframe)
    assert abs(result.delay - 0.030) < 2.5e-5  # measured 4.8e-6 s
    assert 1e-6 < result.std < 3e-5  # measured 6.1e-6 s
    # the spread reported is the folds' standard error: their standard deviation
    # over the square root of their number
    assert len(result.fold_delays) == 2
    assert result.std == pytest.approx(
        np.std(result.fold_delays, ddof=1) / np.sqrt(2), rel=1e-12
    )
    assert "ms" in str(result)
    from lagsindy.joint import conservative_fits

    with conservative_fits():  # the bias itself (a joint fit absorbs it as damping)
        raw = make(system).fit(X, tau, groups=groups)
    fixed = make(system).fit(
        X, shift_input(tau, t, result.delay, groups), groups=groups
    )
    truth = make(system).fit(X, shift_input(tau, t, 0.030, groups), groups=groups)
    ref = {"theta_dot**2": 0.5, "cos(theta)": 9.81}
    for est, bound in ((fixed, 5e-4), (truth, 5e-4)):
        table = est.coef_table().set_index("term")["coefficient"]
        for term, value in ref.items():
            assert abs(table[term] / value - 1) < bound  # measured 0.011 %
    table = raw.coef_table().set_index("term")["coefficient"]
    assert abs(table["theta_dot**2"] / 0.5 - 1) > 0.02  # unshifted: 4.0 % off


@pytest.mark.parametrize("lag", [0.030, 0.0])
def test_support_search_refits_only_while_the_estimate_moves(delayed, lag, fit_rows):
    # With a delay the first fit (at 0) is followed by a refit at the estimate; an
    # estimate that stays where the last fit was made ends the search (no refit of
    # the same input to confirm the support).
    import lagsindy.delay as delay_module

    system, X, tau, t, groups = delayed
    tau = shift_input(tau, t, 0.030 - lag, groups)  # lag 0: the true input
    result = delay_module.estimate_delay(
        make(system), X, tau, t, groups=groups, max_delay=0.048, n_splits=2
    )
    # measured 29.995 ms (2 fits) and -0.0074 ms (0.09 % of the 8 ms sampling
    # interval, under the 1 % within which a refit is skipped; 1 fit)
    assert abs(result.delay - lag) < 4e-5  # measured 4.8e-6 and 7.4e-6 s
    assert len(fit_rows) == (2 if lag else 1)


def test_support_search_fits_delay_zero_on_every_row(delayed, fit_rows):
    # The fit at delay 0 sees the recorded input on every row (no shift runs out
    # of data there); the refit at the estimate only the rows every shift covers.
    system, X, tau, t, groups = delayed
    estimate_delay(make(system), X, tau, t, groups=groups, max_delay=0.048)
    # shifts of up to 6 samples (48 ms at 8 ms) drop the first and last 7 rows of
    # each of the 4 trajectories (the rows within 48 ms of an end, 48 ms included)
    assert fit_rows == [len(X), len(X) - 4 * 2 * 7]


def test_support_search_takes_a_given_first_fit(delayed, fit_rows):
    # A fit given for delay 0 (diagnose's joint fit) replaces the first fit: the
    # estimate is the same, one fit fewer is made.
    import lagsindy.delay as delay_module

    system, X, tau, t, groups = delayed
    first = make(system).fit(X, tau, groups=groups)
    kw = dict(groups=groups, max_delay=0.048, n_splits=2, method="support", verbose=0)
    own = delay_module._estimate_delay(make(system), X, tau, t, **kw)
    assert len(fit_rows) == 3  # the first fit, then the search's two
    fit_rows.clear()
    given = delay_module._estimate_delay(
        make(system), X, tau, t, fitted_at_zero=first, **kw
    )
    assert len(fit_rows) == 1  # the refit at the estimate only
    assert given.delay == own.delay
    np.testing.assert_array_equal(given.scores, own.scores)


def test_delay_needs_held_out_trajectories(delayed):
    system, X, tau, t, groups = delayed
    one = groups == groups[0]
    with pytest.raises(ValueError, match="too short"):
        estimate_delay(make(system), X[one], tau[one], t[one], max_delay=0.9)
    with pytest.raises(ValueError, match="below one sampling interval"):
        estimate_delay(make(system), X, tau, t, groups=groups, max_delay=0.001)


def test_cli_delay_option(tmp_path, capsys, delayed):
    system, X, tau, t, groups = delayed
    frame = pd.DataFrame(
        {
            "trajectory": groups,
            "t": t,
            "theta": X[:, 0],
            "theta_dot": X[:, 1],
            "theta_ddot": X[:, 2],
            "tau_theta": tau[:, 0],
        }
    )
    frame.to_csv(tmp_path / "d.csv", index=False)
    outs = []
    for delay in ("0", "0.03"):
        code = main(
            [
                "fit",
                str(tmp_path / "d.csv"),
                "--coordinates",
                "theta",
                "--angles",
                "theta",
                "--formulation",
                "strong",
                "--delay",
                delay,
                "--conservative",  # the bias itself (a joint fit absorbs it)
                "--out",
                str(tmp_path / "m.json"),
                "--quiet",
            ]
        )
        assert code == 0, capsys.readouterr().err
        outs.append(capsys.readouterr().out)
    coefs = [
        [
            float(c)
            for c in re.findall(r"([-\d.e]+)\*(?:theta_dot\*\*2|cos\(theta\))", o)
        ]
        for o in outs
    ]
    assert np.allclose(coefs[1], [0.5, 9.81], rtol=1e-3), outs[1]  # measured 0.02 %
    assert not np.allclose(coefs[0], [0.5, 9.81], rtol=0.02), outs[0]
    assert (
        main(
            [
                "fit",
                str(tmp_path / "d.csv"),
                "--coordinates",
                "theta",
                "--delay",
                "soon",
                "--out",
                str(tmp_path / "m.json"),
            ]
        )
        == 2
    )
    assert "--delay must be a number" in capsys.readouterr().err


def test_fold_scores_equal_one_least_squares_per_candidate():
    """The delay search's batched least squares (one lstsq per fold, a right-hand
    side per candidate) equals one lstsq per candidate and fold."""
    from sklearn.model_selection import GroupKFold

    from lagsindy.delay import _fold_scores

    rng = np.random.default_rng(0)
    n_rows, n_dof, n_support, n_cand = 300, 2, 4, 9
    groups = np.repeat(np.arange(6), n_rows // 6)
    rows = np.arange(n_rows)
    folds = list(GroupKFold(n_splits=3).split(np.zeros(n_rows), groups=groups))
    A = rng.standard_normal((n_rows * n_dof, n_support))
    # collinear-ish (condition 2e3): the two ways differ by rounding, which grows
    # with the condition (measured 7e-12 at 2e6)
    A[:, 3] = A[:, 2] + 1e-3 * A[:, 3]
    B = A @ rng.standard_normal((n_support, n_cand))
    B = B.T + 0.1 * rng.standard_normal((n_cand, n_rows * n_dof))
    want = np.empty((3, n_cand))
    for f, (train, _) in enumerate(folds):
        tr = np.repeat(np.isin(rows, train), n_dof)
        for c in range(n_cand):
            xi, *_ = np.linalg.lstsq(A[tr], B[c, tr], rcond=None)
            want[f, c] = np.mean((A[~tr] @ xi - B[c, ~tr]) ** 2) / 0.7
    got = _fold_scores(A, B, rows, folds, n_dof, 0.7)
    # measured: equal to 7.5e-15 (relative); a mixed-up fold or candidate shows at 1e-1
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert np.ptp(want) > 1e-1 * want.mean()  # measured 0.39


def test_shifts_for_many_delays_equal_one_shift_each(delayed):
    from lagsindy.delay import _shift_many

    _, _, tau, t, groups = delayed
    tau = np.asarray(tau, dtype=float).reshape(len(t), -1)
    delays = np.array([-0.02, -0.0031, 0.0, 0.004, 0.03])
    many = _shift_many(tau, t, delays, groups)
    for k, d in enumerate(delays):
        # one interpolation per trajectory, input and delay (the definition)
        ref = np.empty_like(tau)
        for g in np.unique(groups):
            rows = np.flatnonzero(groups == g)
            for j in range(tau.shape[1]):
                ref[rows, j] = np.interp(t[rows] - d, t[rows], tau[rows, j])
        np.testing.assert_array_equal(many[k], ref)
        np.testing.assert_array_equal(shift_input(tau, t, d, groups), ref)


def test_least_squares_equals_lstsq_and_falls_back_on_rank_deficiency():
    from lagsindy.delay import _least_squares

    rng = np.random.default_rng(3)
    A = rng.standard_normal((500, 5))
    B = rng.standard_normal((500, 7))
    want = np.linalg.lstsq(A, B, rcond=None)[0]
    # measured: equal to 4e-16 (by QR)
    np.testing.assert_allclose(_least_squares(A, B), want, rtol=1e-12, atol=1e-14)
    A[:, 4] = 2.0 * A[:, 1]  # rank deficient: the minimum-norm solution, as lstsq
    want = np.linalg.lstsq(A, B, rcond=None)[0]
    got = _least_squares(A, B)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


def test_both_methods_on_a_dataframe(delayed):
    # Both methods on named columns: the rows are taken with the DataFrame's
    # columns, so the support search's model (fitted on every row of the frame) is
    # read on the frame's rows without a feature-name warning
    import warnings

    system, X, tau, t, groups = delayed
    names = ["theta", "theta_dot", "theta_ddot"]
    frame = pd.DataFrame(X, columns=names)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        support = estimate_delay(
            make(system), frame, tau, t, groups=groups, max_delay=0.048, n_splits=2
        )
    assert support.delay == pytest.approx(0.030, abs=2.5e-5)  # measured 29.9952 ms
    # method="refit": one sparse fit per candidate and fold
    result = estimate_delay(
        make(system), frame, tau, t, groups=groups, max_delay=0.048, n_splits=2,
        method="refit",
    )  # fmt: skip
    # measured 35.77 ms +- 2.9 ms, the same as with the array (the support search
    # of the first test is closer to the true 30 ms)
    assert result.delay == pytest.approx(0.035769, abs=5e-6)  # measured 35.7686 ms


@pytest.mark.parametrize("k", [2, 3, 5])
def test_the_reported_spread_is_the_standard_error_of_the_folds(k):
    from lagsindy.delay import _finish

    folds = 0.03 + 1e-3 * np.arange(k) ** 2
    scores = np.zeros((k, 3))
    result = _finish(0.031, False, np.arange(3.0), scores, folds, k)
    assert result.std == pytest.approx(np.std(folds, ddof=1) / np.sqrt(k), rel=1e-14)
    assert result.delay == 0.031 and result.fold_delays is folds
    assert np.isnan(_finish(0.03, False, np.arange(3.0), scores[:1], folds[:1], 1).std)


@pytest.mark.parametrize(
    "delay, std, kept",
    [
        (0.1 * 0.01, 0.0, True),  # a tenth of the sampling interval (0.01 s)
        (0.1 * 0.01 * (1 - 1e-9), 0.0, False),
        (-0.002, 0.001 * (1 - 1e-9), True),  # more than twice its standard error
        (-0.002, 0.001, False),
        (0.005, np.nan, True),  # one fold: no standard error to compare with
    ],
)
def test_diagnose_tries_a_delay_of_a_tenth_of_a_sample_and_two_standard_errors(
    delay, std, kept
):
    from lagsindy.delay import DelayEstimate, worth_trying

    estimate = DelayEstimate(delay, std, np.zeros(3), np.zeros((2, 3)), np.zeros(2))
    assert worth_trying(estimate, dt=0.01) is kept


# ---------------------------------------------------------- one delay per column
def test_shift_input_per_column_equals_one_shift_per_column():
    rng = np.random.default_rng(0)
    t = np.r_[np.arange(50), np.arange(40)] * 0.01
    groups = np.r_[np.zeros(50), np.ones(40)]
    tau = rng.standard_normal((90, 3))
    delays = [0.0, 0.013, -0.02]
    out = shift_input(tau, t, delays, groups)
    for j, d in enumerate(delays):
        np.testing.assert_array_equal(out[:, j], shift_input(tau[:, j], t, d, groups))
    with pytest.raises(ValueError, match="one per column"):
        shift_input(tau, t, [0.0, 0.01], groups)


def test_fourier_shift_keeps_the_noise_and_equals_whole_sample_shifts():
    rng = np.random.default_rng(0)
    t = np.arange(4000) * 1e-3
    noise = rng.standard_normal(4000)
    # half a sample: interpolation halves white noise's variance, Fourier keeps it
    assert shift_input(noise, t, 5e-4).var() == pytest.approx(0.5, abs=0.03)
    assert shift_input(noise, t, 5e-4, method="fourier").var() == pytest.approx(
        noise.var(), rel=0.01
    )
    # whole samples: the same as interpolation after the first 7 samples
    np.testing.assert_allclose(
        shift_input(noise, t, 7e-3, method="fourier")[7:],
        shift_input(noise, t, 7e-3)[7:],
        atol=1e-10,
    )
    # a smooth signal shifted by a fraction of a sample (the mirror image's kink
    # rings near the ends only: measured 1.1e-7 from the 50th sample in)
    x = np.sin(3 * t)
    moved = shift_input(x, t, 3.5e-3, method="fourier")
    err = np.abs(moved - np.sin(3 * (t - 3.5e-3)))
    assert err[50:-50].max() < 5e-7
    with pytest.raises(ValueError, match="evenly sampled"):
        shift_input(x, t**1.1, 1e-3, method="fourier")
    with pytest.raises(ValueError, match="method"):
        shift_input(x, t, 1e-3, method="cubic")
