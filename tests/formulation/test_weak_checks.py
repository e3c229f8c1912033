"""lagsindy.formulation.weak: its checks and choices (noise correction, white
velocities, the test window, time order) at their thresholds, and its helpers that
work on all trajectories at once against one trajectory at a time."""

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from _helpers import small_pendulum_library

import lagsindy.formulation.weak as weak_module
from lagsindy import LagrangianSINDy
from lagsindy.formulation.weak import (
    NEGLIGIBLE_NOISE,
    TIME_ORDER_MIN,
    WHITE_VELOCITY,
    WINDOW_CHANGE,
    WindowWarning,
    check_time_order,
    choose_window,
    negligible_noise,
    trajectory_segments,
    weighted_median,
    white_velocities,
    window_change,
)
from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum


# ------------------------------------------------------------- the noise correction
def _two_channels(n=400):
    """Rows of two channels (spreads about 1 and 3) and their one segment."""
    t = np.linspace(0, 1, n)
    X = torch.tensor(np.c_[np.sin(7 * t), 3 * np.cos(5 * t)])
    return X, [torch.arange(n)], X.std(dim=0)


@pytest.mark.parametrize(
    "levels, negligible",
    [
        ((1 - 1e-6, 1 - 1e-6), True),  # every channel just at the level
        ((1 + 1e-6, 1 - 1e-6), False),  # one channel just above
        ((1 - 1e-6, 1 + 1e-6), False),
        ((0.0, 2.0), False),  # one clean channel does not make the noise negligible
        ((0.0, 0.0), True),
    ],
)
def test_noise_is_negligible_only_when_every_channel_is(levels, negligible):
    X, segments, spread = _two_channels()
    sd = NEGLIGIBLE_NOISE * spread * torch.tensor(levels, dtype=X.dtype)
    cov = torch.diag(sd**2)
    assert negligible_noise(X, segments, cov) is negligible
    assert negligible_noise(X, segments, None) is True  # no correction asked


@pytest.fixture(scope="module")
def noisy_velocities():
    """Exact positions (an encoder), white noise 0.1 on the velocities."""
    system = single_pendulum()
    d = make_dataset(
        system, n_trajectories=10, duration=4.0, excitation="sincos", random_state=0
    )
    X = np.array(d.X_clean)
    X[:, 1] += 0.1 * np.random.default_rng(1).standard_normal(len(X))
    return system, d, X


def test_noise_on_one_channel_is_corrected(noisy_velocities):
    """The positions are clean, the velocities are not: the correction applies (a
    check that skipped it when any one channel was clean left the coefficients
    2.7 % off, against 0.35 % with it, and no sign of it)."""
    system, d, X = noisy_velocities
    est = LagrangianSINDy(system.paper_library(), formulation="weak").fit(
        X, d.tau, groups=d.groups
    )
    assert est.noise_cov_ is not None
    # measured: velocity noise variance 0.0100 estimated, positions' below 1e-9
    assert est.noise_cov_[1, 1] == pytest.approx(0.01, rel=0.05)
    assert est.noise_cov_[0, 0] < 1e-8
    truth = {"theta_dot**2": 0.5, "cos(theta)": 9.81}
    table = est.coef_table().set_index("term")["coefficient"]
    assert sorted(table[table != 0].index) == sorted(truth)
    worst = max(abs(table[k] / v - 1) for k, v in truth.items())
    assert worst < 0.017  # measured 0.35 %


# ------------------------------------------------------------- white velocities
@pytest.mark.parametrize("factor, white", [(1 - 1e-6, False), (1 + 1e-6, True)])
def test_velocities_count_as_white_just_above_the_level(factor, white):
    """A velocity whose fourth differences are known exactly: a ramp (none) plus an
    alternating sequence a (-1)^s (16 a (-1)^s), so its white-noise level is
    16 a / sqrt(70)."""
    n = 2001
    ramp = np.linspace(-1.0, 1.0, n)
    spread = ramp.std(ddof=1)  # the alternation adds 1e-8 relative at most
    a = factor * WHITE_VELOCITY * spread * np.sqrt(70) / 16
    qd = ramp + a * (-1.0) ** np.arange(n)
    X = torch.tensor(np.c_[np.zeros(n), qd, np.zeros(n)])
    assert white_velocities(X, [torch.arange(n)], 1) is white


# ------------------------------------------------------------- the test window
def _ladder_of(coefs):
    """Statistics functions of windows 81, 161, ... whose solves give ``coefs``."""
    windows = [81 * 2**k - (2**k - 1) for k in range(len(coefs))]
    by_window = dict(zip(windows, coefs))
    ladder = [lambda w=w: SimpleNamespace(window=w) for w in windows]

    def solve(stats, like=None):
        return SimpleNamespace(coef=np.asarray(by_window[stats.window], dtype=float))

    return ladder, solve


def _rotated(change):
    """``a`` and ``b``, of equal norms, whose window_change is ``change``."""
    a = np.array([1.0, 0.5])
    phi = 2 * np.arcsin(change / 2)
    rotation = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    return a, rotation @ a


@pytest.mark.parametrize("factor, settled", [(1 - 1e-6, True), (1 + 1e-6, False)])
def test_a_window_is_kept_when_the_next_moves_it_by_at_most_the_change(factor, settled):
    a, b = _rotated(factor * WINDOW_CHANGE)
    assert window_change(a, b) == pytest.approx(factor * WINDOW_CHANGE, rel=1e-12)
    ladder, solve = _ladder_of([a, b])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stats, solution = choose_window(ladder, solve)
    assert stats.window == 81  # kept when settled; the first one when not
    np.testing.assert_array_equal(solution.coef, a)
    assert [w.category for w in caught] == ([] if settled else [WindowWarning])
    if not settled:
        assert "windows of 81, 161 samples" in str(caught[0].message)


def test_the_window_moves_on_while_the_coefficients_change():
    a = np.array([1.0, 0.5])
    far = a * (1 + 4 * WINDOW_CHANGE)
    near = far * (1 + 0.5 * WINDOW_CHANGE)
    ladder, solve = _ladder_of([a, far, near])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        stats, solution = choose_window(ladder, solve)
    assert stats.window == 161  # confirmed by 321
    np.testing.assert_array_equal(solution.coef, far)
    # other terms count as an infinite change
    assert window_change(a, np.array([1.0, 0.0])) == np.inf


# ------------------------------------------------------------- time order
@pytest.mark.parametrize("order, ordered", [(TIME_ORDER_MIN, True), (0.1999, False)])
def test_rows_count_as_time_ordered_from_the_minimum_correlation(
    monkeypatch, order, ordered
):
    d = make_dataset(single_pendulum(), n_trajectories=4, duration=2.0, random_state=0)
    monkeypatch.setattr(weak_module, "check_time_order", lambda *a, **k: order)
    est = LagrangianSINDy(small_pendulum_library(), formulation="weak")
    if ordered:
        assert est.fit(d.X, d.tau, groups=d.groups).formulation_ == "weak"
    else:
        with pytest.raises(ValueError, match="do not look like time-ordered"):
            est.fit(d.X, d.tau, groups=d.groups)


# ---------------------------------------- all trajectories at once, against one by one
def _sorted_weighted_median(r, w):
    """The previous implementation: full sort, cumulative weights."""
    r, w = torch.as_tensor(r), torch.as_tensor(w)
    order = torch.argsort(r)
    cum = torch.cumsum(w[order], 0)
    k = int(torch.searchsorted(cum, cum[-1] / 2))
    return float(r[order][min(k, r.numel() - 1)])


@pytest.mark.parametrize("n", [1, 2, 7, 600, 5001])
def test_weighted_median_by_selection_equals_the_sorted_one(n):
    rng = np.random.default_rng(n)
    cases = [
        (rng.normal(size=n), rng.random(n)),
        (rng.integers(-4, 4, n).astype(float), rng.random(n)),  # ties
        (rng.integers(-2, 2, n).astype(float), np.ones(n)),  # ties, equal weights
        (rng.normal(size=n), rng.integers(0, 3, n).astype(float)),  # zero weights
    ]
    # exactly half the weight below the middle value: the lower one is the median
    cases.append((np.repeat([0.0, 1.0], [n // 2 + n % 2, n // 2]), np.ones(n)))
    for values, weights in cases:
        if weights.sum() == 0:
            continue
        assert weighted_median(values, weights) == _sorted_weighted_median(
            values, weights
        )


def _per_segment_time_order(X, n_dof, segments, lags=(1, 2, 4, 8, 16, 32)):
    """The previous implementation: one segment at a time."""
    tracks = []
    for seg in segments:
        q, qd = X[seg, :n_dof], X[seg, n_dof : 2 * n_dof]
        trap = torch.cumsum((qd[1:] + qd[:-1]) / 2, dim=0)
        tracks.append((q, torch.cat([trap.new_zeros((1, n_dof)), trap])))
    best = 0.0
    for k in lags:
        long_enough = [(q, cum) for q, cum in tracks if q.shape[0] > k]
        if not long_enough:
            break
        a = torch.cat([(q[k:] - q[:-k]).flatten() for q, _ in long_enough])
        b = torch.cat([(cum[k:] - cum[:-k]).flatten() for _, cum in long_enough])
        den = float(torch.sqrt((a * a).sum() * (b * b).sum()))
        if den > 0:
            best = max(best, float((a * b).sum()) / den)
    return best


def test_time_order_on_all_segments_at_once_equals_per_segment():
    data = make_dataset(
        cart_pendulum(), n_trajectories=6, excitation="sincos", random_state=0
    )
    X = torch.tensor(data.X)
    segments = trajectory_segments(X, 2, data.groups)
    rng = np.random.default_rng(0)
    short = [s[: int(rng.integers(1, 40))] for s in segments]  # some shorter than lags
    noisy = X + 0.05 * torch.tensor(rng.normal(size=X.shape))
    shuffled = X[torch.as_tensor(rng.permutation(X.shape[0]))]
    for x, segs in [
        (X, segments),
        (X, short),
        (noisy, segments),
        (shuffled, segments),
        (X, [s[:1] for s in segments]),  # no pair at any lag
    ]:
        want = _per_segment_time_order(x, 2, segs)
        # measured: 1.1e-16 at most (the integrals run over all segments at once)
        assert check_time_order(x, 2, segs) == pytest.approx(want, abs=1e-12)
    assert check_time_order(X, 2, segments) > 0.99
    assert check_time_order(X, 2, []) == 0.0
    # enough=: the lags stop once one reaches it; the verdict is the same
    for x in (X, noisy, shuffled):
        full = check_time_order(x, 2, segments)
        quick = check_time_order(x, 2, segments, enough=0.2)
        assert (quick >= 0.2) == (full >= 0.2)
        assert quick == full or full >= quick >= 0.2
    # measured on the noisy rows: lag 1 0.213 (returned with enough=0.2), all lags
    # 0.989, the first lag reaching 0.9 0.960
    lag_one = _per_segment_time_order(noisy, 2, segments, lags=(1,))
    assert check_time_order(noisy, 2, segments, enough=0.2) == pytest.approx(lag_one)
    assert 0.2 <= lag_one < 0.3
    assert 0.9 <= check_time_order(noisy, 2, segments, enough=0.9) < 0.98


def _per_segment_jump(X, n_dof, segments, dt):
    """The previous gap check, one segment at a time: (segment, step) or None."""
    q, qd = X[:, :n_dof], X[:, n_dof : 2 * n_dof]
    for k, rows in enumerate(segments):
        rows = np.asarray(rows)
        if rows.size < 3:
            continue
        step = np.diff(q[rows], axis=0)
        expected = dt * (qd[rows][1:] + qd[rows][:-1]) / 2
        mismatch = np.abs(step - expected)
        centre = np.median(mismatch, axis=0)
        spread = 1.4826 * np.median(np.abs(mismatch - centre), axis=0)
        jump = np.abs(step) > 4 * np.abs(expected) + 10 * spread + 1e-12
        if jump.any():
            return k, int(np.flatnonzero(jump.any(axis=1))[0])
    return None


def test_segment_helpers_at_once_equal_one_segment_at_a_time():
    """trajectory_segments (labels by a sort), estimate_sampling_interval and
    check_weak_form_segments (segments of one length stacked) against loops over
    the labels and segments: the same rows, dt and first jump, bit for bit."""
    from lagsindy.differentiation import check_weak_form_segments
    from lagsindy.formulation.weak import estimate_sampling_interval, weighted_median

    data = make_dataset(
        cart_pendulum(), n_trajectories=6, excitation="sincos", random_state=1
    )
    rng = np.random.default_rng(2)
    X = data.X.copy()
    mixed = np.array(["b", "a", "c", "a", "b", "c"])[data.groups]  # not sorted
    got = trajectory_segments(torch.tensor(X), 2, mixed)
    want = [np.flatnonzero(mixed == v) for v in ("b", "a", "c")]  # first seen
    assert [s.tolist() for s in got] == [w.tolist() for w in want]
    labels = np.array(["d", "b", "f", "a", "e", "c"])[data.groups]
    X[1230:, :2] += 0.3  # a jump inside the third trajectory (rows 1000-1499)
    X[2300:, :2] -= 0.3  # and one inside the fifth: the first is reported
    Xt = torch.tensor(X)
    segments = trajectory_segments(Xt, 2, labels)
    assert [int(s[0]) for s in segments] == [0, 500, 1000, 1500, 2000, 2500]
    cut = [s[: int(rng.integers(2, 500))] for s in segments] + [segments[0][:1]]
    for segs in (segments, cut):
        parts = [s.numpy() for s in segs]
        ratios, weights = [], []
        for rows in parts:
            if rows.size < 2:
                continue
            q, qd = X[rows, :2], X[rows, 2:4]
            mid = (qd[1:] + qd[:-1]) / 2
            ok = np.abs(mid) > 0
            ratios.append((q[1:] - q[:-1])[ok] / mid[ok])
            weights.append(mid[ok] ** 2)
        dt = estimate_sampling_interval(Xt, 2, segs)
        assert dt == weighted_median(np.concatenate(ratios), np.concatenate(weights))
        found = _per_segment_jump(X, 2, parts, 0.01)
        if found is None:
            check_weak_form_segments(X, 2, parts, 0.01)
            continue
        k, s = found
        rows = parts[k]
        with pytest.raises(ValueError, match=f"trajectory {k} .*rows {rows[s]} and"):
            check_weak_form_segments(X, 2, parts, 0.01)
    assert _per_segment_jump(X, 2, [s.numpy() for s in segments], 0.01)[0] == 2


def test_fourth_differences_at_once_equal_one_segment_at_a_time():
    """The noise covariance and the white-velocity check take the fourth differences
    of all segments at once: the same as one ``torch.diff`` per segment (segments
    shorter than 5 rows, and in any order, included), bit for bit."""
    from lagsindy.formulation.weak import (
        WHITE_VELOCITY,
        estimate_noise_covariance,
        white_velocities,
    )

    rng = np.random.default_rng(3)
    X = torch.tensor(rng.normal(size=(60, 6)))
    for segs in (
        [torch.arange(0, 25), torch.arange(25, 28), torch.arange(28, 60)],
        [torch.arange(40, 60), torch.arange(0, 40)],
        [torch.arange(0, 4)],
    ):
        parts = [torch.diff(X[s, :4], n=4, dim=0) for s in segs if len(s) > 4]
        want = (
            torch.zeros(4, 4, dtype=X.dtype)
            if not parts
            else (lambda z: z.T @ z / (70.0 * z.shape[0]))(torch.cat(parts))
        )
        assert torch.equal(estimate_noise_covariance(X, segs, 2), want)
        qd = [X[s, 2:4] for s in segs if len(s) > 4]
        if qd:
            level = torch.sqrt(
                torch.cat([torch.diff(v, n=4, dim=0) for v in qd]).pow(2).mean(0) / 70
            )
            white = bool((level > WHITE_VELOCITY * torch.cat(qd).std(dim=0)).all())
        else:
            white = False
        assert white_velocities(X, segs, 2) == white
    # rows given as arrays or lists, as the 0.1 module path's users may pass them
    as_arrays = [np.arange(0, 25), list(range(25, 60))]
    as_tensors = [torch.arange(0, 25), torch.arange(25, 60)]
    assert torch.equal(
        estimate_noise_covariance(X, as_arrays, 2),
        estimate_noise_covariance(X, as_tensors, 2),
    )
