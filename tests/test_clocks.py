"""Real clocks (#40): clock cleaning, edges, test functions in time, resampling.

Each clock defect is pinned on a small synthetic record (sums of sines, so that the
exact derivatives are known); tolerances sit near the measured values (in comments).
"""

import warnings

import numpy as np
import pytest
import torch

from lagsindy.differentiation import (
    ClockWarning,
    clean_clock,
    derivatives,
    quadrature_weights,
    resample,
    time_test_functions,
    trapezoid_weights,
)
from lagsindy.differentiation import clock as clock_module

W1, W2 = 2 * np.pi * 0.7, 2 * np.pi * 1.9


def motion(t):
    """Two coordinates with their exact velocities and accelerations."""
    q = np.c_[np.sin(W1 * t) + 0.3 * np.sin(W2 * t), np.cos(W1 * t + 0.4)]
    qd = np.c_[
        W1 * np.cos(W1 * t) + 0.3 * W2 * np.cos(W2 * t), -W1 * np.sin(W1 * t + 0.4)
    ]
    qdd = np.c_[
        -(W1**2) * np.sin(W1 * t) - 0.3 * W2**2 * np.sin(W2 * t),
        -(W1**2) * np.cos(W1 * t + 0.4),
    ]
    return q, qd, qdd


def rel_rms(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2) / np.mean(b**2)))


def caught(fn):
    with warnings.catch_warnings(record=True) as found:
        warnings.simplefilter("always")
        out = fn()
    return out, [str(w.message) for w in found if issubclass(w.category, ClockWarning)]


# ----------------------------------------------------------------- even clocks
def test_an_even_clock_is_left_exactly_as_it_was():
    t = np.arange(600) * 0.01
    q = motion(t)[0] + 1e-3 * np.random.default_rng(0).standard_normal((600, 2))
    groups = np.repeat([0, 1], 300)
    (X, clock), messages = caught(
        lambda: derivatives(q, t, groups=groups, return_clock=True)
    )
    np.testing.assert_array_equal(X, derivatives(q, t, groups=groups, clean=False))
    assert messages == [] and not clock.changed
    assert clock.keep.all() and np.array_equal(clock.t, t) and clock.valid.all()
    assert clock.groups.tolist() == groups.tolist()
    assert clock.report == (
        "12 row(s) lie within 3 sample(s) of a segment's end (one-sided derivative "
        "estimates, several times less accurate): flagged in edge",
    )


# ----------------------------------------------------------------- stale rows
def logged(t, stale_rows):
    q, qd, _ = motion(t)
    source = np.arange(t.size)
    for r in stale_rows:
        source[r] = source[r - 1]
    return q[source], qd[source]


def test_stale_rows_are_dropped_and_carry_their_source():
    t = np.arange(800) * 0.002
    stale = [50, 51, 300, 611]  # a run of two, and two single ones
    q, _ = logged(t, stale)
    (X, clock), messages = caught(lambda: derivatives(q, t, return_clock=True))
    assert clock.defects["stale"].tolist() == stale
    assert clock.source[[50, 51, 300]].tolist() == [49, 49, 299]
    assert not clock.keep[stale].any() and clock.keep.sum() == 796
    np.testing.assert_array_equal(X[51], X[49])
    assert len(messages) == 2  # the stale rows and the steps they leave
    assert messages[0].startswith("4 row(s) repeat the previous row's positions")
    exact = motion(t)[2]
    inner = clock.keep & ~clock.edge
    # measured 4.7e-5 cleaned, 0.12 with the stale rows left in
    assert rel_rms(X[inner, 4:], exact[inner]) < 5e-4
    kept_in = derivatives(q, t, clean=False)
    assert rel_rms(kept_in[inner, 4:], exact[inner]) > 0.05


def test_interleaved_stale_rows_are_all_found():
    # a fresh row between two runs of repeats: the steps around each run are
    # themselves catch-up jumps (measured before the per-cycle rule: 2 of 4 missed,
    # each leaving a q_ddot spike of ~100 rad/s^2 at noise 1e-5)
    t = np.arange(400) * 0.001
    stale = [100, 102, 103, 105]
    q, _ = logged(t, stale)
    assert clean_clock(t, q).defects["stale"].tolist() == stale


def test_a_repeat_ending_a_trajectory_is_stale_only_in_motion():
    for last, stale in ((0.49e-3, False), (0.51e-3, True)):  # half the median step
        step = np.r_[1e-7, np.full(30, 1e-3), [last, 0.0]]
        assert (
            clock_module._stale_rows(np.cumsum(np.r_[0.0, step])[:, None])[-1] == stale
        )


def test_a_turning_point_or_a_slow_step_is_no_stale_row():
    # an encoder sitting on one reading while the motion turns (sign change), and
    # steps below 0.03 median steps around a repeat: kept
    # (one tiny step sets the encoder's resolution far below the steps tested)
    step = np.r_[1e-7, np.full(20, 1e-3), [2e-4, 0.0, -3e-4], np.full(20, -1e-3)]
    q = np.cumsum(np.r_[0.0, step])
    assert not clock_module._stale_rows(q[:, None]).any()
    for around, stale in ((0.029e-3, False), (0.031e-3, True)):  # STALE_MIN_STEP
        step = np.r_[
            1e-7,
            np.full(20, 1e-3),
            [around, 0.0, 2 * around, around],
            np.full(20, 1e-3),
        ]
        q = np.cumsum(np.r_[0.0, step])
        assert clock_module._stale_rows(q[:, None]).any() == stale
    # nor a repeat where the steps around it are within 3 resolutions
    step = np.r_[np.full(20, 1e-3), [1e-3, 0.0, 2e-3], np.full(20, 1e-3)]
    assert not clock_module._stale_rows(np.cumsum(np.r_[0.0, step])[:, None]).any()


def test_a_stale_row_needs_the_jump_after_it_to_catch_up():
    # r = 1 repeat: the jump must reach 0.75 * 2 = 1.5 times the steps around it
    for jump, stale in ((1.49e-3, False), (1.51e-3, True)):
        step = np.r_[1e-7, np.full(20, 1e-3), [0.0, jump], np.full(20, 1e-3)]
        q = np.cumsum(np.r_[0.0, step])
        assert clock_module._stale_rows(q[:, None]).any() == stale


# ----------------------------------------------------------------- near-duplicates
def test_near_duplicate_stamps_are_merged_just_below_a_quarter_step():
    t = np.arange(300) * 0.01
    q = motion(t)[0]
    for fraction, merged in ((0.24, True), (0.26, False)):
        stamps = t.copy()
        stamps[100] = stamps[99] + fraction * 0.01
        clock = clean_clock(stamps, q)
        assert (clock.defects["duplicate"].tolist() == [100]) == merged
    equal = t.copy()
    equal[100] = equal[99]  # an equal stamp: merged, no error
    (X, clock), messages = caught(lambda: derivatives(q, equal, return_clock=True))
    assert clock.source[100] == 99 and np.array_equal(X[100], X[99])
    assert any(
        m.startswith("1 row(s) come less than 0.25 median steps") for m in messages
    )
    back = t.copy()
    back[100] = back[99] - 0.003  # back by 0.3 steps: refused
    with pytest.raises(ValueError, match=r"row 100 has t = 0.987 after t = 0.99 "):
        derivatives(q, back)


def test_close_stamps_of_an_irregular_clock_are_samples():
    t = np.sort(np.random.default_rng(1).uniform(0, 4, 400))
    clock = clean_clock(t, motion(t)[0], gap_factor=None)
    assert clock.keep.all() and clock.report[:-1] == ()


# ----------------------------------------------------------------- gaps, drops, short
def test_dropped_frames_are_kept_and_integrated_over():
    rng = np.random.default_rng(2)
    t = np.arange(1000) * 0.01
    keep = rng.random(1000) >= 0.15
    q = motion(t)[0] + 1e-4 * rng.standard_normal((1000, 2))
    t, q = t[keep], q[keep]
    (X, clock), messages = caught(lambda: derivatives(q, t, return_clock=True))
    assert np.unique(clock.groups).tolist() == [0]  # not cut
    assert clock.defects["dropped"].size == 120
    assert len(messages) == 1 and "dropped frames" in messages[0]
    inner = ~clock.edge
    # measured 1.62e-3 (the same samples on the even clock, none dropped: 1.57e-3)
    assert rel_rms(X[inner, 4:], motion(t)[2][inner]) < 3e-3


def test_gaps_cut_and_a_short_segment_between_two_gaps_is_bridged():
    t = np.arange(1000) * 0.01
    keep = np.ones(1000, dtype=bool)
    keep[300:320] = keep[324:350] = False  # a 4-sample piece between two gaps
    t = t[keep]
    q = motion(t)[0]
    (X, groups, clock), messages = caught(
        lambda: derivatives(q, t, return_groups=True, return_clock=True)
    )
    assert np.unique(groups).tolist() == [0, 1, 2]
    assert clock.defects["short"].tolist() == [300, 301, 302, 303]
    assert np.isfinite(X).all() and clock.edge[300:304].all() and clock.valid.all()
    assert any("too few to differentiate on their own" in m for m in messages)
    assert any(m.startswith("2 gap(s) in the time stamps") for m in messages)
    # measured 1.1e-3 (noise-free): the spline across the gaps
    assert rel_rms(X[300:304, 4:], motion(t)[2][300:304]) < 1e-2


def test_a_short_segment_with_no_neighbour_gets_nan_and_is_not_valid():
    t = np.r_[np.arange(50), np.arange(80, 84)] * 0.01
    groups = np.r_[np.zeros(50), np.zeros(4)]
    (X, clock), _ = caught(lambda: derivatives(motion(t)[0], t, return_clock=True))
    assert np.isfinite(X).all()  # bridged with the first segment
    t2 = np.r_[np.arange(5), np.arange(30, 35), np.arange(60, 65)] * 0.01
    with pytest.raises(ValueError, match="needs at least 7 samples"):
        derivatives(motion(t2)[0][:5], t2[:5])
    del groups


# ----------------------------------------------------------------- jitter and cycles
def test_truthful_jittered_stamps_are_kept_silently():
    rng = np.random.default_rng(3)
    t = np.arange(2000) * 0.01 + rng.uniform(-0.3, 0.3, 2000) * 0.01
    q = motion(t)[0] + 1e-3 * rng.standard_normal((2000, 2))
    (X, clock), messages = caught(lambda: derivatives(q, t, return_clock=True))
    assert messages == [] and clock.period is None and np.array_equal(clock.t, t)


def test_stamps_jittering_around_an_even_clock_are_rebuilt_on_it():
    rng = np.random.default_rng(4)
    t = np.arange(2000) * 0.01
    q = motion(t)[0] + 1e-4 * rng.standard_normal((2000, 2))
    stamps = t + rng.uniform(-0.2, 0.2, 2000) * 0.01
    (X, clock), messages = caught(lambda: derivatives(q, stamps, return_clock=True))
    assert clock.period == pytest.approx(0.01, rel=1e-5)
    np.testing.assert_allclose(np.diff(clock.t), 0.01, rtol=1e-5)
    assert any("disagree with the motion" in m for m in messages)
    inner = ~clock.edge
    exact = motion(t)[2]
    # measured 1.45e-3 rebuilt (1.45e-3 on the true clock), 0.020 on the stamps
    assert rel_rms(X[inner, 4:], exact[inner]) < 3e-3
    raw = derivatives(q, stamps, clean=False)
    assert rel_rms(raw[inner, 4:], exact[inner]) > 0.01


def logger(seed, gaussian, noise=1e-5, seconds=3.0):
    """An exact 1 kHz cycle, 2 % of the cycles skipped, 5 % stale rows, stamps
    with 0.3 ms of jitter; returns (q, v, stamps, true times, stale mask)."""
    rng = np.random.default_rng(seed)
    cycles = np.arange(int(seconds * 1000))
    cycles = cycles[np.r_[True, rng.random(cycles.size - 1) >= 0.02]]
    t = cycles * 1e-3
    stale = np.r_[False, rng.random(t.size - 1) < 0.05]
    q, v, _ = motion(t)
    q = q + noise * rng.standard_normal(q.shape)
    source = np.arange(t.size)
    for r in np.flatnonzero(stale):
        source[r] = source[r - 1]
    q, v = q[source], v[source]
    jitter = (
        rng.normal(0, 3e-4, t.size) if gaussian else rng.uniform(-3e-4, 3e-4, t.size)
    )
    return q, v, t + jitter, t, stale


@pytest.mark.parametrize(
    "gaussian, velocities, bound",
    # measured 4.1e-6, 6.2e-6 (with the velocities), 3.5e-5 (counted from the motion)
    [(False, False, 2e-5), (True, True, 3e-5), (True, False, 2e-4)],
)
def test_a_logger_clock_is_rebuilt_on_its_cycle(gaussian, velocities, bound):
    q, v, stamps, t, stale = logger(5, gaussian)
    clock = clean_clock(stamps, q, velocities=v if velocities else None)
    X = derivatives(q, stamps, clean=clock)
    assert clock.period == pytest.approx(1e-3, rel=1e-4)  # measured 3e-6 .. 1.8e-5
    fresh = ~stale
    truth = derivatives(q[fresh], t[fresh], clean=False)
    rows = np.flatnonzero(fresh)
    inner = clock.keep[rows] & ~clock.edge[rows]
    assert rel_rms(X[rows][inner, 4:], truth[inner, 4:]) < bound
    assert np.array_equal(np.flatnonzero(stale), clock.defects["stale"])


def test_the_stamps_of_a_logger_clock_as_given_are_far_off():
    q, _, stamps, t, stale = logger(5, False)
    raw = derivatives(q, stamps, clean=False)
    fresh = ~stale
    truth = derivatives(q[fresh], t[fresh], clean=False)
    rows = np.flatnonzero(fresh)[10:-10]
    # measured 0.012 (cleaned: 4e-6, above): the spline follows the stamps' jitter
    assert rel_rms(raw[rows, 4:], truth[10:-10, 4:]) > 5e-3
    q, _, stamps, _, _ = logger(5, True)  # Gaussian jitter: stamps go back
    with pytest.raises(ValueError, match="strictly increasing"):
        derivatives(q, stamps, clean=False)


@pytest.mark.parametrize("ratio, rebuilt", [(0.89, True), (0.91, False)])
def test_the_motion_decides_the_rebuild_at_a_ratio_of_0_9(monkeypatch, ratio, rebuilt):
    monkeypatch.setattr(clock_module, "_motion_ratio", lambda *a, **k: ratio)
    t = np.arange(500) * 0.01
    stamps = t + np.random.default_rng(6).uniform(-0.2, 0.2, 500) * 0.01
    clock = clean_clock(stamps, motion(t)[0])
    assert (clock.period is not None) == rebuilt
    assert clean_clock(stamps, motion(t)[0], rebuild=False).period is None


# ----------------------------------------------------------------- edges
def test_edge_rows_are_flagged_where_the_error_is_largest():
    rng = np.random.default_rng(7)
    t = np.arange(3000) * 0.01
    groups = np.repeat(np.arange(10), 300)
    q = motion(t)[0] + 1e-3 * rng.standard_normal((3000, 2))
    X, clock = derivatives(q, t, groups=groups, return_clock=True)
    assert clock.edge.sum() == 60
    first = np.flatnonzero(np.r_[True, np.diff(groups) != 0])
    assert clock.edge[first].all() and clock.edge[first + 2].all()
    assert not clock.edge[first + 3].any()
    err = (X[:, 4:] - motion(t)[2]) ** 2
    # measured: edge rows 4.4x the RMS error of the rest, 28 % of the squared error
    ratio = np.sqrt(err[clock.edge].mean() / err[~clock.edge].mean())
    assert ratio > 2.5
    assert clean_clock(t, q, groups, edge_samples=0).edge.sum() == 0


# ----------------------------------------------------------------- test functions
@pytest.mark.parametrize(
    "n, window, stride, dt", [(500, 81, 20, 0.01), (333, 41, 10, 1e-3)]
)
def test_time_test_functions_equal_the_bump_on_an_even_clock(n, window, stride, dt):
    from lagsindy.formulation.testfunctions import _correlate, bump_function

    rng = np.random.default_rng(8)
    t = 3.7 + np.arange(n) * dt
    a, b = rng.standard_normal((n, 2, 5)), rng.standard_normal((n, 2, 5))
    psi, dpsi = bump_function(window, dt)
    expected = -dt * (
        _correlate(torch.tensor(a), dpsi, stride)
        + _correlate(torch.tensor(b), psi, stride)
    )
    got = time_test_functions(t, (window - 1) * dt, stride * dt).columns(a, b)
    scale = np.max(np.abs(expected.numpy()))
    assert np.max(np.abs(got - expected.numpy())) <= 1e-12 * scale  # measured 2e-13


@pytest.mark.parametrize(
    "kind, trapezoid, corrected",
    # measured integration-by-parts mismatch: 1.9e-4 -> 2.6e-6, 1.6e-3 -> 3.7e-5
    [("jitter", 1e-3, 1e-5), ("drops", 5e-3, 1.5e-4)],
)
def test_time_test_functions_integrate_by_parts_on_uneven_steps(
    kind, trapezoid, corrected
):
    rng = np.random.default_rng(0)
    if kind == "jitter":
        t = np.arange(200) * 0.01 + rng.uniform(-0.3, 0.3, 200) * 0.01
    else:
        t = np.arange(230) * 0.01
        t = t[rng.random(230) > 0.15]
    out = {}
    for rule in ("trapezoid", "corrected"):
        w = time_test_functions(t, 0.8, 0.2, quadrature=rule)
        lhs = w.columns(np.sin(3 * t), 0 * t)
        rhs = -w.columns(0 * t, 3 * np.cos(3 * t))
        out[rule] = np.max(np.abs(lhs - rhs)) / np.max(np.abs(rhs))
    assert out["corrected"] < corrected < trapezoid and out["trapezoid"] < trapezoid
    assert out["trapezoid"] > 10 * out["corrected"]


def test_quadrature_weights_are_the_trapezoid_on_an_even_grid():
    t = 0.3 + np.arange(100) * 0.01
    np.testing.assert_array_equal(quadrature_weights(t), trapezoid_weights(t))
    uneven = np.r_[0.0, 0.01, 0.03, 0.04, 0.05]
    assert not np.allclose(quadrature_weights(uneven), trapezoid_weights(uneven))


def test_windows_stay_inside_the_segment_and_short_segments_get_one():
    t = np.arange(101) * 0.01  # 1 s
    w = time_test_functions(t, 0.4, 0.1)
    assert w.n_windows == 7 and w.starts[-1] + w.window <= t[-1] + 1e-12
    assert np.abs(w.a.toarray()[:, [0, -1]]).max() < 1e-12  # psi' is 0 at the ends
    for samples, windows in ((8, 0), (9, 1)):  # MIN_WINDOW_SAMPLES = 9
        short = np.arange(samples) * 0.01
        got = time_test_functions(short, 0.4, 0.1)
        assert got.n_windows == windows
    one = time_test_functions(np.arange(20) * 0.01, 0.4, 0.1)
    assert one.window == pytest.approx(0.19) and one.n_windows == 1
    a2, ab, b2 = w.sample_weights()
    assert a2.shape == (101,) and (b2 >= 0).all()
    with pytest.raises(ValueError, match="strictly increasing"):
        time_test_functions(t[::-1], 0.4, 0.1)


# ----------------------------------------------------------------- resampling
def test_resample_puts_an_uneven_record_on_an_even_clock():
    rng = np.random.default_rng(9)
    t = np.arange(1500) * 0.01 + rng.uniform(-0.3, 0.3, 1500) * 0.01
    t = t[rng.random(1500) >= 0.1]
    q = motion(t)[0] + 1e-3 * rng.standard_normal((t.size, 2))
    tau = np.c_[np.sin(t), np.cos(2 * t)]
    (out, messages) = caught(lambda: resample(q, t, 0.01, tau=tau))
    assert messages == [] and out.dt == 0.01
    np.testing.assert_allclose(np.diff(out.t), 0.01, rtol=1e-9)
    inner = slice(5, -5)
    # measured 8.0e-3 (an even clock with the same noise: 7.5e-3)
    assert rel_rms(out.X[inner, 4:], motion(out.t)[2][inner]) < 0.02
    # linear interpolation (measured 2e-4 at most, across dropped frames)
    np.testing.assert_allclose(out.tau[:, 0], np.sin(out.t), atol=1e-3)


def test_invalid_clock_arguments():
    t = np.arange(30) * 0.1
    q = np.sin(t)
    with pytest.raises(ValueError, match="rebuild must be"):
        clean_clock(t, q, rebuild="yes")
    with pytest.raises(ValueError, match="period must be"):
        clean_clock(t, q, period=-1.0)
    with pytest.raises(ValueError, match="velocities must be finite"):
        clean_clock(t, q, velocities=np.ones((29, 1)))
    with pytest.raises(ValueError, match="clean must be True, False or a CleanedClock"):
        derivatives(q, t, clean="yes")
    with pytest.raises(ValueError, match="CleanedClock of 30 rows, but q has 29"):
        derivatives(q[:-1], t[:-1], clean=clean_clock(t, q))
    with pytest.raises(ValueError, match="return_clock=True needs"):
        derivatives(q, t, clean=False, return_clock=True)
    with pytest.raises(ValueError, match="window must be a positive"):
        time_test_functions(t, 0.0, 0.1)


@pytest.mark.parametrize("name", ["clock", "_timegrid", "resample", "core"])
def test_the_examples_in_the_docstrings_run(name):
    import doctest
    import importlib

    module = importlib.import_module(f"lagsindy.differentiation.{name}")
    with warnings.catch_warnings():
        warnings.simplefilter("error", ClockWarning)
        result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
    assert result.failed == 0 and result.attempted > 0


def test_the_python_blocks_of_docs_clocks_run_on_their_own():
    # each block in its own namespace (none leans on another), all in one fresh
    # interpreter (a fresh one per block costs the imports four times)
    import os
    import re
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    text = (root / "docs" / "clocks.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) == 6
    runner = (
        "import sys\nfor code in sys.argv[1:]:\n    exec(code, {'__name__': 'doc'})"
    )
    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run(
        [sys.executable, "-c", runner, *blocks], capture_output=True, text=True, env=env
    )
    assert done.returncode == 0, done.stderr[-2000:]


def test_the_most_likely_counts_increase_and_follow_the_motion():
    from lagsindy.differentiation.cycle import _most_likely_counts

    x = np.array([0.0, 1.6, 1.4, 3.0])  # stamps alone would count 0, 2, 1, 3
    none = np.full(3, np.inf)
    assert _most_likely_counts(x, np.zeros(3), none, 0.3).tolist() == [0, 1, 2, 3]
    # a precise motion says the second step covers two cycles
    steps, sigma = np.array([1.0, 2.0, 1.0]), np.full(3, 0.05)
    x = np.array([0.0, 1.2, 2.6, 4.1])
    assert _most_likely_counts(x, steps, sigma, 0.3).tolist() == [0, 1, 3, 4]
