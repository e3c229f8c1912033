"""Edge rows (#40, item 2) and refits given the fit's clock.

Derivative estimates at a segment's ends are one-sided and several times less
accurate than the interior's (``benchmarks/results/clocks.md``, section 4). A fit
given time stamps (``fit(X, tau, t=...)``) leaves the rows within 3 samples of a
segment's end out; ``bootstrap`` and ``diagnose`` take the same ``t=`` and refuse to
run without it on a model fitted with it. Tolerances sit near the measured values
(in comments).
"""

import dataclasses
import types
import warnings

import numpy as np
import pytest

from benchmarks import clocks as bench
from lagsindy import LagrangianSINDy, bootstrap, diagnose, refine
from lagsindy.differentiation import clean_clock, derivatives, edge_rows
from lagsindy.formulation import AutoForm
from lagsindy.formulation.clocked import frame_on_clock
from lagsindy.joint import conservative_fits
from lagsindy.systems import single_pendulum


# -------------------------------------------------------------------- edge_rows
@pytest.mark.parametrize("m, all_flagged", [(6, True), (7, False)])
def test_a_segment_shorter_than_min_samples_is_all_edge(m, all_flagged):
    t = np.r_[np.arange(m), 100 + np.arange(20)] * 0.01  # a gap after row m - 1
    edge = edge_rows(t, min_samples=7)
    assert bool(edge[:m].all()) is all_flagged
    if not all_flagged:  # 7 rows: 3 at each end, the middle one kept
        assert np.flatnonzero(~edge[:m]).tolist() == [3]
    assert np.flatnonzero(~edge[m:]).tolist() == list(range(3, 17))


@pytest.mark.parametrize("step, cut", [(0.0499, False), (0.0501, True)])
def test_a_step_longer_than_gap_factor_median_steps_cuts(step, cut):
    t = np.r_[np.arange(20) * 0.01, 0.19 + step + np.arange(20) * 0.01]
    edge = edge_rows(t, gap_factor=5.0)
    assert bool(edge[[19, 20]].all()) is cut  # the rows either side of the step
    assert edge.sum() == (12 if cut else 6)


def test_edge_rows_of_the_cleaned_times_are_the_clock_edges():
    rng = np.random.default_rng(3)
    t = bench.camera_clock(800, rng, 0.2, 0.05, 4, 8.0)
    q = np.c_[np.sin(2 * t), np.cos(3 * t)]
    clock = clean_clock(t, q)
    rows = clock.rows
    assert clock.edge.sum() > 20  # 4 gaps, and a short segment or not
    np.testing.assert_array_equal(edge_rows(clock.t[rows]), clock.edge[rows])


# ------------------------------------------------------------- fits, edge-heavy
def _camera(forced, n_traj, duration, n_gaps, seed=0):
    sys_ = bench.system()
    n = int(round(duration * bench.RATE))

    def clock(k, rng):
        return bench.camera_clock(n, rng, 0.2, 0.05, n_gaps, duration)

    rec = bench.records(sys_, n_traj, duration, forced, seed, clock)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        X, clk = derivatives(
            rec["q"], rec["t"], groups=rec["groups"], angles="all", return_clock=True
        )
    return sys_, rec, X, clk


def _terms(est):
    return set(est.coef_table().query("kept")["term"])


def test_an_edge_heavy_record_gives_the_true_terms_in_the_weak_form():
    """10 gaps per 6 s record (segments of 34 samples at the median): with the
    edge rows, a short segment's rows made the weak form refuse the record and
    the strong form returned 52 terms; without them, exactly the true terms."""
    sys_, rec, X, clk = _camera(True, 6, 6.0, 10)
    library = sys_.paper_library()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = LagrangianSINDy(library).fit(X, rec["tau"], t=clk)
        kept_edges = dataclasses.replace(clk, edge=np.zeros_like(clk.edge))
        old = LagrangianSINDy(library).fit(X, rec["tau"], t=kept_edges)
    truth = bench.true_terms(sys_, est.library_)
    assert est.formulation_ == "weak" and _terms(est) == truth
    true = dict(zip(map(str, est.library_.terms_), sys_.true_coefficients(library)))
    coef = est.coef_table().query("kept").set_index("term")["coefficient"]
    err = max(abs(c / true[k] - 1) for k, c in coef.items())
    assert err < 0.007  # measured 0.14 %
    assert est.clock_["edge_rows"] == int(clk.edge.sum()) > 200  # 9.6 % of rows
    assert "left out of the fit" in est.clock_["report"]
    assert old.formulation_ == "strong" and _terms(old) != truth


def test_the_strong_form_given_time_stamps_leaves_the_edge_rows_out():
    """Passive, 8 gaps per 5 s: the strong form with the edge rows returned 26
    terms; without them the true 6 (ratios within 0.5 %)."""
    sys_, rec, X, clk = _camera(False, 3, 5.0, 8)
    library = sys_.paper_library()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = LagrangianSINDy(library, formulation="strong").fit(X, t=clk)
        rows = np.flatnonzero(~clk.edge)
        same = LagrangianSINDy(library, formulation="strong").fit(X[rows])
    np.testing.assert_allclose(est.coef_, same.coef_, rtol=1e-10, atol=1e-12)
    assert _terms(est) == bench.true_terms(sys_, est.library_)
    assert est.clock_["dt"] is None and est.clock_["fit_rows"] == rows.size


def test_fits_without_time_stamps_have_no_clock():
    t = np.arange(300) * 0.01
    X = np.c_[np.sin(2 * t), 2 * np.cos(2 * t), -4 * np.sin(2 * t)]
    est = LagrangianSINDy(single_pendulum().paper_library()).fit(X)
    assert not hasattr(est, "clock_")


# -------------------------------------------------- bootstrap and diagnose with t=
@pytest.fixture(scope="module")
def damped():
    """A damped single pendulum on a camera clock, fitted (conservative) with its
    time stamps."""
    system = single_pendulum().with_damping(viscous={"theta": 0.2})
    rng = np.random.default_rng(0)
    parts = {"q": [], "t": [], "g": [], "tau": []}
    x0 = system.sample_initial_states(12, np.random.RandomState(0))
    for k in range(12):
        tt = bench.camera_clock(300, rng, 0.2, 0.05, 1, 3.0)

        def u_fn(s, _x, k=k):
            return np.array([np.sin((1.5 + 0.2 * k) * s)])

        X = system.trajectory_to_X(
            system.simulate(x0[k], tt, u_fn), np.stack([u_fn(s, None) for s in tt])
        )
        parts["q"].append(X[:, :1] + 1e-4 * rng.standard_normal((tt.size, 1)))
        parts["t"].append(tt)
        parts["g"].append(np.full(tt.size, k))
        parts["tau"].append(np.stack([u_fn(s, None) for s in tt]))
    q, t, g, tau = (np.concatenate(parts[k]) for k in ("q", "t", "g", "tau"))
    with warnings.catch_warnings(), conservative_fits():  # diagnose adds the damping
        warnings.simplefilter("ignore")
        X, clock = derivatives(q, t, groups=g, angles="all", return_clock=True)
        est = LagrangianSINDy(system.paper_library(), formulation="strong")
        est.fit(X, tau, groups=g, t=clock)
    return est, X, tau, g, clock


def test_bootstrap_refuses_a_model_fitted_with_time_stamps_without_them(damped):
    est, X, tau, g, _ = damped
    with pytest.raises(ValueError, match="pass the same t= to bootstrap"):
        bootstrap(est, X, tau, groups=g, n_resamples=2)


def test_bootstrap_given_the_time_stamps_repeats_the_fit(damped):
    est, X, tau, g, clock = damped
    with warnings.catch_warnings(), conservative_fits():  # as est was fitted
        warnings.simplefilter("ignore")
        report = bootstrap(
            est, X, tau, groups=g, t=clock, n_resamples=4, random_state=0
        )
    table = report.to_frame().set_index("term")
    full = est.coef_table().set_index("term")["coefficient"]
    np.testing.assert_allclose(
        table.loc[full.index, "coefficient"], full, rtol=1e-10, atol=1e-12
    )


def test_diagnose_refuses_a_model_fitted_with_time_stamps_without_them(damped):
    est, X, tau, g, _ = damped
    with pytest.raises(ValueError, match="pass the same t= to diagnose"):
        diagnose(est, X, tau, groups=g)


def test_diagnose_given_the_time_stamps_finds_the_damping(damped):
    est, X, tau, g, clock = damped
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = diagnose(est, X, tau, groups=g, t=clock, catalogue=["viscous"])
    assert report.effects == ["viscous(theta)"]
    # measured 0.2001
    assert report.steps[0].coefficient == pytest.approx(0.2, rel=0.01)


def test_refine_refuses_a_model_fitted_with_time_stamps_without_them(damped):
    est, X, tau, g, _ = damped
    with pytest.raises(ValueError, match="pass the same t= to refine"):
        refine(est, X, tau, groups=g)


def test_refine_given_the_time_stamps_rolls_out_on_the_even_clock(damped):
    """Given the fit's stamps, refine rolls out on the fit's even clock (the uneven
    rows as they are would cut a window at every jittered step)."""
    est, X, tau, g, clock = damped
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = refine(est, X, tau, groups=g, t=clock, horizon=40, max_iter=5)
    rep = out.refinement_
    # measured: 127 windows of 40 samples on the even clock (on the uneven rows
    # every jittered step cut a window: "no trajectory has 41 samples without a
    # gap"); the rollout error of the conservative model falls 0.0133 -> 0.0021
    assert rep.n_windows >= 100
    assert rep.rmse_after < 0.3 * rep.rmse_before


def test_the_python_rows_are_the_cli_rows():
    """bootstrap/diagnose given t= see the rows the CLI fits (edges left out, the
    weak form's rows on an even clock)."""
    import pandas as pd

    from lagsindy.cli._io import _on_even_clock

    _, rec, X, clk = _camera(True, 2, 4.0, 2)
    names = ["theta1", "theta2", "theta1_dot", "theta2_dot"]
    names += ["theta1_ddot", "theta2_ddot"]
    frame = pd.DataFrame(X, columns=names)
    py_X, py_tau, py_g, form = frame_on_clock(
        AutoForm(), frame, rec["tau"], rec["groups"], clk
    )
    args = types.SimpleNamespace(_t=clk.t, _edge=clk.edge, quiet=True)
    cli_X, cli_tau, cli_g, dt = _on_even_clock(args, frame, rec["tau"], rec["groups"])
    np.testing.assert_array_equal(np.asarray(py_X), np.asarray(cli_X))
    np.testing.assert_array_equal(py_tau, cli_tau)
    assert form.dt == dt and list(py_X.columns) == names
