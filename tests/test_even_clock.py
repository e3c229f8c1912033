"""Fits given time stamps (#40, phase 2): ``to_even_clock`` and ``fit(..., t=)``.

The weak form takes consecutive rows as ``dt`` apart; ``fit(X, tau, t=...)`` puts
an uneven clock's rows on an even clock first. Tolerances sit near the measured
values (in comments).
"""

import warnings

import numpy as np
import pytest

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy.differentiation import derivatives, edge_rows, to_even_clock
from lagsindy.formulation import AutoForm


def states(t):
    """[q, qd, qdd] of two coordinates (sums of sines), exact."""
    w1, w2 = 2.1, 5.3
    q = np.c_[np.sin(w1 * t), 0.5 * np.cos(w2 * t)]
    qd = np.c_[w1 * np.cos(w1 * t), -0.5 * w2 * np.sin(w2 * t)]
    qdd = np.c_[-(w1**2) * np.sin(w1 * t), -0.5 * w2**2 * np.cos(w2 * t)]
    return np.c_[q, qd, qdd]


def uneven(n=600, dt=0.01, jitter=0.2, drop=0.05, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt + rng.uniform(-jitter, jitter, n) * dt
    t[0] = 0.0
    keep = rng.random(n) >= drop
    keep[[0, -1]] = True
    return np.sort(t[keep])


# ----------------------------------------------------------------- to_even_clock
def test_the_hermite_interpolant_is_exact_for_a_quintic():
    t = uneven()
    c = np.array([0.3, -1.0, 0.5, 2.0, -0.7, 0.4])
    p = np.polynomial.Polynomial(c)
    X = np.c_[p(t), p.deriv(1)(t), p.deriv(2)(t)]
    out = to_even_clock(X, t, dt=0.01)
    exact = np.c_[p(out.t), p.deriv(1)(out.t), p.deriv(2)(out.t)]
    # measured 4e-14 (rounding)
    np.testing.assert_allclose(out.X, exact, atol=1e-11)
    assert out.changed and np.allclose(np.diff(out.t), 0.01)


def test_uneven_rows_land_on_an_even_clock_near_the_exact_states():
    t = uneven()
    out = to_even_clock(states(t), t)
    exact = states(out.t)
    err = np.max(np.abs(out.X - exact), axis=0)
    # measured: q 2e-11, qd 2e-9, qdd 1.1e-6 (the interpolant's own error)
    assert err[:2].max() < 1e-10 and err[2:4].max() < 1e-8 and err[4:].max() < 5e-6
    # the frame step (measured 0.009998), dropped frames counted as frames
    assert out.dt == pytest.approx(0.01, rel=1e-3)
    assert "1 of 1 segment(s) put on an even clock" in out.report
    assert f"({t.size} rows -> {out.t.size}" in out.report


def test_an_even_clock_is_returned_as_it_was():
    t = np.arange(500) * 0.01
    X = states(t)
    tau = np.c_[np.sin(t), np.cos(t)]
    out = to_even_clock(X, t, np.repeat([0, 1], 250), tau)
    assert not out.changed and out.report == ""
    np.testing.assert_array_equal(out.X, X)
    np.testing.assert_array_equal(out.tau, tau)
    np.testing.assert_array_equal(out.groups, np.repeat([0, 1], 250))


def test_gaps_cut_repeated_rows_left_out():
    t = np.r_[np.arange(300) * 0.01, 3.5 + np.arange(300) * 0.01]
    X = states(t)
    X[100] = X[99]  # a row carried over from its source (stale, dropped)
    t[100] = t[99]
    out = to_even_clock(X, t)
    assert np.unique(out.groups).size == 2  # cut at the 0.51 s gap
    assert "1 repeated or near-duplicate row(s) left out" in out.report
    np.testing.assert_allclose(out.X, states(out.t), atol=2e-3)


@pytest.mark.parametrize("fraction, merged", [(0.24, True), (0.26, False)])
def test_a_near_duplicate_stamp_is_left_out_below_a_quarter_step(fraction, merged):
    t = np.arange(400) * 0.01
    t = np.sort(np.r_[t, t[200] + fraction * 0.01])
    out = to_even_clock(states(t), t, dt=0.01)
    assert ("near-duplicate" in out.report) is merged


def test_a_time_going_back_is_refused():
    t = np.arange(100) * 0.01
    t[[50, 51]] = t[[51, 50]]
    with pytest.raises(ValueError, match="t goes back at row 51"):
        to_even_clock(states(t), t)
    with pytest.raises(ValueError, match="one time per row"):
        to_even_clock(states(t), t[:-1])
    with pytest.raises(ValueError, match="gap_factor"):
        to_even_clock(states(t), np.sort(t), gap_factor=1)


# ----------------------------------------------------------------- fit(..., t=)
@pytest.fixture(scope="module")
def pendulum_records():
    """A forced double pendulum (4 x 6 s, 100 Hz nominal, noise 1e-3 rad) on an
    even clock and on a camera clock (20 % jitter, 5 % dropped, two gaps)."""
    from benchmarks.clocks import camera_clock, records, system

    sys_ = system()
    n, duration = 600, 6.0
    even = records(sys_, 4, duration, True, 0, lambda k, rng: np.arange(n) / 100)
    cam = records(
        sys_, 4, duration, True, 0,
        lambda k, rng: camera_clock(n, rng, 0.2, 0.05, 2, duration),
    )  # fmt: skip
    return sys_.paper_library(), even, cam


def _fit(library, rec, *, t=True):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        X, clock = derivatives(
            rec["q"], rec["t"], groups=rec["groups"], angles="all", return_clock=True
        )
        est = LagrangianSINDy(library)
        if t:
            return est.fit(X, rec["tau"], t=clock)
        return est.fit(X, rec["tau"], groups=clock.groups)


def _largest_difference(a, b):
    assert np.array_equal(a.support_, b.support_)
    keep = b.support_
    return float(np.max(np.abs(a.coef_[keep] / b.coef_[keep] - 1)))


def test_the_fit_given_time_stamps_matches_the_even_clock(pendulum_records):
    library, even, cam = pendulum_records
    ref = _fit(library, even, t=False)
    got = _fit(library, cam)
    # measured 0.12 % (acceptance: 1 %); the former path (no t): 8.7 % off
    assert _largest_difference(got, ref) < 0.004
    assert got.formulation_ == "weak" and got.dt_ == pytest.approx(0.01, rel=3e-3)
    # without the stamps the weak form takes the rows as evenly spaced: off
    old = _fit(library, cam, t=False)
    assert old.formulation_ == "strong" or _largest_difference(old, ref) > 0.02


def test_time_stamps_of_an_even_clock_change_nothing_but_dt_and_edges(
    pendulum_records,
):
    """On an even clock, t= only sets dt and leaves out the 3 rows at each end of
    every trajectory (edge_rows)."""
    library, even, _ = pendulum_records
    X = derivatives(even["q"], even["t"], groups=even["groups"], angles="all")
    inner = ~edge_rows(even["t"], even["groups"])
    assert inner.sum() == X.shape[0] - 6 * len(np.unique(even["groups"]))
    a = LagrangianSINDy(library, formulation=AutoForm(dt=0.01)).fit(
        X[inner], even["tau"][inner], groups=even["groups"][inner]
    )
    b = LagrangianSINDy(library).fit(X, even["tau"], groups=even["groups"], t=even["t"])
    np.testing.assert_allclose(b.coef_, a.coef_, rtol=1e-10, atol=1e-12)
    assert b.clock_["edge_rows"] == X.shape[0] - inner.sum()
    assert b.clock_["fit_rows"] == inner.sum() and b.clock_["rows"] == X.shape[0]


@pytest.mark.parametrize("longest, strong", [(80, True), (81, False)])
def test_the_strong_form_only_when_no_segment_holds_a_window(longest, strong):
    """Segments shorter than the weak form's first window (81 samples, after the 3
    edge rows at each end are left out): the strong form, with a warning saying it
    is the only option left and why."""
    rng = np.random.default_rng(1)
    pieces, t0 = [], 0.0
    for m in [longest + 6] + [60] * 9:
        local = np.arange(m) * 0.01
        local[1:-1] += rng.uniform(-0.2, 0.2, m - 2) * 0.01  # ends exact
        pieces.append(t0 + local)
        t0 = pieces[-1][-1] + 0.5  # a gap
    t = np.concatenate(pieces)
    X = np.c_[
        np.sin(2 * t), np.cos(3 * t), 2 * np.cos(2 * t), -3 * np.sin(3 * t),
        -4 * np.sin(2 * t), -9 * np.cos(3 * t),
    ]  # fmt: skip
    from lagsindy.formulation.clocked import rows_on_even_clock
    from lagsindy.formulation.forms import AutoForm, StrongForm

    with warnings.catch_warnings(record=True) as found:
        warnings.simplefilter("always")
        Xe, _, groups, form, clock = rows_on_even_clock(AutoForm(), X, None, None, t)
    said = [str(w.message) for w in found]
    inner = ~edge_rows(t)
    assert np.bincount(to_even_clock(X[inner], t[inner]).groups).max() == longest
    assert isinstance(form, StrongForm) is strong
    assert any("the only option left" in s for s in said) is strong
    if strong:
        assert (
            f"has {longest} samples, fewer than the weak form's window of 81"
            in (said[0])
        )
        # the strong form takes the rows as they are, less the edge rows
        np.testing.assert_array_equal(Xe, X[inner])
        assert clock["edge_rows"] == 60 and clock["dt"] is None


def test_a_cleaned_clock_must_be_of_the_same_rows():
    t = np.arange(300) * 0.01
    q = states(t)[:, :2]
    X, clock = derivatives(q, t, return_clock=True)
    est = LagrangianSINDy(CandidateLibrary.polynomial(["q0", "q1"], degree=2))
    with pytest.raises(ValueError, match="CleanedClock of 300 rows, but X has 299"):
        est.fit(X[:-1], t=clock)
