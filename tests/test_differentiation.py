"""Derivative estimation: accuracy, trajectory boundaries, angles, time stamps, API."""

import pickle
import warnings

import numpy as np
import pandas as pd
import pytest
from sklearn.base import clone
from sklearn.model_selection import GroupKFold, cross_val_score
from sklearn.pipeline import make_pipeline
from sklearn.utils.estimator_checks import parametrize_with_checks

from lagsindy import Derivatives, LagrangianSINDy, derivatives
from lagsindy.differentiation import METHODS
from lagsindy.systems import make_dataset, single_pendulum

FAST = [
    m for m in METHODS if m != "spline"
]  # scipy's GCV spline is slow: used sparingly
W1, W2 = np.pi, 2.6 * np.pi  # 0.5 Hz and 1.3 Hz


def signal(t):
    """q, q_dot, q_ddot of a two-tone test signal."""
    q = np.sin(W1 * t) + 0.3 * np.sin(W2 * t)
    qd = W1 * np.cos(W1 * t) + 0.3 * W2 * np.cos(W2 * t)
    qdd = -(W1**2) * np.sin(W1 * t) - 0.3 * W2**2 * np.sin(W2 * t)
    return q, qd, qdd


def rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


T = np.arange(500) / 100.0  # 5 s at 100 Hz, as in the paper
T_JITTER = T + 0.003 * np.random.default_rng(1).uniform(-1, 1, T.size)


# ----------------------------------------------------------------- accuracy
# (method, kwargs, bound on RMS error of q_dot, of q_ddot); noise-free, uniform 100 Hz.
# Measured: pspline 5e-8 / 2e-5, savgol 1.3e-4 / 9e-3, finite_difference 2e-3 / 8e-3.
@pytest.mark.parametrize(
    "method, kwargs, bound_qd, bound_qdd",
    [
        ("pspline", {}, 1e-6, 1e-4),
        ("savgol", {}, 5e-4, 2e-2),
        ("finite_difference", {}, 4e-3, 1.6e-2),
    ],
)
@pytest.mark.parametrize("t", [T, T_JITTER], ids=["uniform", "non-uniform"])
def test_noise_free_accuracy(method, kwargs, bound_qd, bound_qdd, t):
    q, qd, qdd = signal(t)
    X = derivatives(q, t, method=method, **kwargs)
    assert X.shape == (t.size, 3)
    assert rms(X[:, 1] - qd) < bound_qd
    if method == "finite_difference" and t is T_JITTER:
        # the 3-point second difference is first order where steps differ
        bound_qdd = 0.3
    assert rms(X[:, 2] - qdd) < bound_qdd


def test_cubic_spline_is_accurate_inside_and_natural_at_the_ends():
    q, qd, qdd = signal(T)
    X = derivatives(q, T, method="spline")
    assert rms(X[:, 1] - qd) < 1e-2
    assert rms((X[:, 2] - qdd)[30:-30]) < 1e-2
    # a natural cubic spline has zero curvature at both ends, whatever the data
    assert abs(X[0, 2]) < 1e-6 and abs(X[-1, 2]) < 1e-6


@pytest.mark.parametrize("jitter", [False, True])
def test_finite_difference_is_second_order_including_the_ends(jitter):
    errors = []
    for h in (0.02, 0.01):
        t = np.arange(0, 3 + h / 2, h)
        if jitter:
            t = t + 0.2 * h * np.sin(7.3 * np.arange(t.size))
        q, qd, qdd = signal(t)
        X = derivatives(q, t, method="finite_difference")
        errors.append([np.max(np.abs(X[:, 1] - qd)), np.max(np.abs(X[:, 2] - qdd))])
    ratio = np.array(errors[0]) / np.array(errors[1])
    assert ratio[0] > 3.5  # first derivative: second order on any grid
    if not jitter:
        assert ratio[1] > 3.5  # second derivative: second order on a uniform grid


def test_exact_on_polynomials_with_non_uniform_times():
    t = np.sort(np.random.default_rng(2).uniform(0, 2, 60))
    c = [0.3, -1.2, 0.7, 0.25, -0.4]  # a quartic
    q = np.polyval(c[::-1], t)
    qd = np.polyval(np.polyder(c[::-1]), t)
    qdd = np.polyval(np.polyder(c[::-1], 2), t)
    X = derivatives(q, t, method="savgol", window=9, polyorder=4)
    np.testing.assert_allclose(X, np.c_[q, qd, qdd], atol=1e-8)
    quad = 1.0 - 2.0 * t + 0.5 * t**2
    X = derivatives(quad, t, method="finite_difference")
    np.testing.assert_allclose(X, np.c_[quad, -2.0 + t, np.ones_like(t)], atol=1e-7)
    # the P-spline penalty (4th differences of the coefficients when the smoothing is
    # fixed) vanishes on cubics: heavy smoothing leaves them unchanged
    cubic = quad + 0.2 * t**3
    X = derivatives(cubic, t, method="pspline", smoothing=1e6)
    np.testing.assert_allclose(X[:, 2], 1.0 + 1.2 * t, atol=1e-5)


def test_noisy_accuracy():
    q, qd, qdd = signal(T)
    rng = np.random.default_rng(0)
    # bounds about twice the measured errors (pspline 0.32, 0.89; savgol 31: 0.21, 1.9)
    for sigma, bound_qd, bound_qdd, bound_wide in [
        (1e-3, 0.02, 0.6, 0.4),
        (1e-2, 0.07, 1.5, 3.0),
    ]:
        y = q + sigma * rng.normal(size=T.size)
        X = derivatives(y, T)  # default: pspline with GCV
        assert rms(X[:, 1] - qd) < bound_qd
        assert rms(X[:, 2] - qdd) < bound_qdd
        # Savitzky-Golay with a window suited to the noise does well; the default
        # 11-sample window does not smooth enough for q_ddot at these noise levels
        wide = derivatives(y, T, method="savgol", window=31)
        narrow = derivatives(y, T, method="savgol", window=11)
        assert rms(wide[:, 2] - qdd) < bound_wide
        assert rms(narrow[:, 2] - qdd) > 5 * rms(X[:, 2] - qdd)
        # finite differences amplify white noise by sqrt(6) / dt^2 in q_ddot
        fd = derivatives(y, T, method="finite_difference")
        expected = sigma * np.sqrt(6) / 0.01**2
        assert 0.8 * expected < rms((fd[:, 2] - qdd)[5:-5]) < 1.2 * expected


def test_cubic_spline_with_noise():
    q, qd, qdd = signal(T)
    y = q + 1e-2 * np.random.default_rng(0).normal(size=T.size)
    X = derivatives(y, T, method="spline")
    assert rms(X[:, 1] - qd) < 0.12
    assert rms(X[:, 2] - qdd) < 3.0


# ----------------------------------------------------------------- no tuning needed
@pytest.mark.parametrize("sigma", [1e-3, 1e-2])
def test_gcv_smoothing_is_close_to_the_best_fixed_one(sigma):
    q, _, qdd = signal(T)
    y = q + sigma * np.random.default_rng(3).normal(size=T.size)
    auto = rms(derivatives(y, T)[:, 2] - qdd)
    best = min(
        rms(derivatives(y, T, smoothing=s)[:, 2] - qdd) for s in np.logspace(-4, 7, 45)
    )
    assert auto < 1.5 * best


@pytest.mark.parametrize("method", FAST)
def test_units_do_not_matter(method):
    """Rescaling q by a and time by c rescales the derivatives by a/c and a/c^2.

    For the P-spline this holds with the smoothing chosen automatically: the same
    call serves millimetres and kilometres, milliseconds and hours.
    """
    q, _, _ = signal(T)
    y = q + 1e-2 * np.random.default_rng(4).normal(size=T.size)
    X = derivatives(y, T, method=method)
    for a, c in [(1e-3, 1e-3), (1e3, 3600.0)]:
        Y = derivatives(a * y, c * T, method=method)
        np.testing.assert_allclose(Y[:, 0], a * X[:, 0], rtol=1e-6, atol=1e-9 * a)
        np.testing.assert_allclose(
            Y[:, 1], a / c * X[:, 1], rtol=1e-6, atol=1e-9 * a / c
        )
        np.testing.assert_allclose(
            Y[:, 2], a / c**2 * X[:, 2], rtol=1e-6, atol=1e-9 * a / c**2
        )


def test_each_coordinate_gets_its_own_smoothing():
    q, _, qdd = signal(T)
    rng = np.random.default_rng(5)
    # a clean coordinate next to a noisy one of another scale
    Y = np.c_[q, 100 * q + rng.normal(size=T.size)]
    X = derivatives(Y, T)
    assert rms(X[:, 4] - qdd) < 1e-3
    alone = derivatives(Y[:, 1], T)
    np.testing.assert_allclose(X[:, [1, 3, 5]], alone, rtol=1e-10, atol=1e-10)


# ----------------------------------------------------------------- trajectories
@pytest.mark.parametrize("method", FAST)
def test_no_leakage_across_trajectories(method):
    t1 = np.arange(120) * 0.01
    t2 = np.arange(80) * 0.01  # the second trajectory restarts its clock
    q1 = np.sin(2 * t1)
    q2 = 5.0 + np.cos(3 * t2)  # a jump of ~5 at the boundary
    together = derivatives(
        np.r_[q1, q2],
        np.r_[t1, t2],
        groups=np.r_[np.zeros(120), np.ones(80)],
        method=method,
    )
    apart = np.r_[
        derivatives(q1, t1, method=method), derivatives(q2, t2, method=method)
    ]
    np.testing.assert_allclose(together, apart, rtol=1e-12, atol=1e-12)
    # a differentiator that ignored the boundary would see the jump
    leaky = derivatives(np.r_[q1, q2], np.r_[t1, t2 + 1.2], method=method)
    assert np.max(np.abs(leaky[115:125, 1] - apart[115:125, 1])) > 1.0


def test_group_labels_may_be_any_hashable_in_any_order():
    t = np.r_[np.arange(50), np.arange(50), np.arange(50)] * 0.02
    q = np.r_[np.sin(t[:50]), np.cos(t[50:100]), t[100:] ** 2]
    ints = derivatives(q, t, groups=np.repeat([0, 1, 2], 50))
    strings = derivatives(q, t, groups=np.repeat(["c", "a", "b"], 50))
    np.testing.assert_array_equal(ints, strings)


def test_scalar_dt_restarts_the_clock_per_trajectory():
    rng = np.random.default_rng(6)
    q = rng.normal(size=(90, 2)).cumsum(axis=0)
    groups = np.repeat([4, 9], [40, 50])
    t = np.r_[np.arange(40), np.arange(50)] * 0.05
    np.testing.assert_allclose(
        derivatives(q, 0.05, groups=groups), derivatives(q, t, groups=groups)
    )


# ----------------------------------------------------------------- angles
def test_angles_are_unwrapped_per_trajectory():
    t = np.arange(400) * 0.01
    theta = 2.5 * t - 0.5  # four turns in 4 s, constant speed
    wrapped = np.angle(np.exp(1j * theta))
    noisy_free = np.c_[wrapped, 0.1 * t]  # a second, non-angular coordinate
    X = derivatives(noisy_free, t, angles=[0], method="savgol")
    np.testing.assert_allclose(X[:, 2], 2.5, atol=1e-6)
    np.testing.assert_allclose(X[:, 4], 0.0, atol=1e-5)
    np.testing.assert_allclose(X[:, 0], theta, atol=1e-9)  # q comes back unwrapped
    for spec in ([True, False], np.array([True, False]), [-2]):
        np.testing.assert_allclose(
            derivatives(noisy_free, t, angles=spec, method="savgol"), X
        )
    with pytest.warns(UserWarning, match=r"\[0\] look like wrapped angles"):
        wrong = derivatives(noisy_free, t, method="savgol")
    assert np.max(np.abs(wrong[:, 2])) > 100  # the wraps look like huge velocities
    # two trajectories: each is unwrapped from its own first sample
    both = derivatives(
        np.r_[wrapped, wrapped[::-1]],
        np.r_[t, t],
        groups=np.repeat([0, 1], 400),
        angles="all",
        method="pspline",
    )
    np.testing.assert_allclose(both[:400, 1], 2.5, atol=1e-4)
    np.testing.assert_allclose(both[400:, 1], -2.5, atol=1e-4)
    assert abs(both[400, 0] - wrapped[-1]) < 1e-6


# ----------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(method="kalman"), "method must be one of"),
        (dict(method="savgol", window=10), "window must be an odd integer"),
        (dict(method="savgol", polyorder=1), "polyorder must be an integer >= 2"),
        (
            dict(method="savgol", window=5, polyorder=5),
            "polyorder must be less than window",
        ),
        (dict(angles=[3]), "angles must hold coordinate indices"),
        (dict(angles=[True]), "boolean mask needs one entry per coordinate"),
        (dict(smoothing=-1.0), "smoothing must be None"),
        (
            dict(groups=np.zeros(5)),
            "groups must be 1-D with one trajectory label per row",
        ),
        (
            dict(groups=np.repeat([0, 1, 0], [10, 10, 10])),
            "trajectory 0 are not contiguous",
        ),
    ],
)
def test_invalid_arguments(kwargs, match):
    t = np.arange(30) * 0.1
    with pytest.raises(ValueError, match=match):
        derivatives(np.c_[np.sin(t), np.cos(t)], t, **kwargs)


def test_invalid_data():
    t = np.arange(30) * 0.1
    q = np.sin(t)
    with pytest.raises(ValueError, match="q contains 1 NaN"):
        derivatives(np.where(t == 1.0, np.nan, q), t)
    with pytest.raises(ValueError, match="t contains 1 NaN or infinite"):
        derivatives(q, np.where(t == 1.0, np.inf, t))
    with pytest.raises(ValueError, match="one time stamp per row"):
        derivatives(q, t[:-1])
    # (an equal stamp is a near-duplicate the clock cleaning merges; a stamp going
    # back by more than a quarter step is refused, tests/test_clocks.py)
    with pytest.raises(ValueError, match="strictly increasing within each trajectory"):
        derivatives(q, np.r_[t[:10], t[9] - 0.05, t[11:]])
    with pytest.raises(ValueError, match="pass groups="):
        derivatives(np.r_[q, q], np.r_[t, t])  # two stacked trajectories, no labels
    with pytest.raises(ValueError, match=r"row 31 \(trajectory 'b'\) has t = 2.8"):
        derivatives(np.r_[q, q], np.r_[t, t[::-1]], groups=np.repeat(["a", "b"], 30))
    with pytest.raises(ValueError, match="sampling interval must be finite and > 0"):
        derivatives(q, 0.0)
    with pytest.raises(ValueError, match="q must be 2-D"):
        derivatives(np.zeros((30, 2, 2)), t)


def test_short_trajectories():
    t = np.arange(7) * 0.1
    quad = 1 + t + t**2
    with pytest.warns(UserWarning, match="shorter than window=11"):
        X = derivatives(quad, t, method="savgol")
    np.testing.assert_allclose(X[:, 2], 2.0, atol=1e-9)
    X = derivatives(quad, t, method="pspline")
    np.testing.assert_allclose(X[:, 2], 2.0, atol=1e-6)
    with pytest.raises(
        ValueError, match=r"needs at least 7 samples .* trajectory 1 has 6"
    ):
        derivatives(
            np.r_[quad, quad[:6]], np.r_[t, t[:6]], groups=np.repeat([0, 1], [7, 6])
        )
    with pytest.raises(ValueError, match="needs at least 3 samples"):
        derivatives(quad[:2], t[:2], method="finite_difference")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        derivatives(quad[:3], t[:3], method="finite_difference")


# ----------------------------------------------------------------- transformer
@pytest.fixture(scope="module")
def pendulum():
    """Single pendulum, 10 trajectories x 3 s; encoder noise 1e-3 rad on theta alone."""
    data = make_dataset(
        single_pendulum(), n_trajectories=10, duration=3.0, random_state=0
    )
    frame = data.to_frame()[["trajectory", "t", "theta"]].copy()
    frame["theta"] = data.X_clean[:, 0] + 1e-3 * np.random.default_rng(0).normal(
        size=len(frame)
    )
    return data, frame


def test_transformer_on_a_dataframe(pendulum):
    data, frame = pendulum
    frame = frame.set_index(np.arange(len(frame)) + 1000)
    out = Derivatives().fit_transform(frame)
    assert list(out.columns) == ["theta", "theta_dot", "theta_ddot"]
    assert out.index.equals(frame.index)
    expected = derivatives(frame[["theta"]], frame["t"], groups=frame["trajectory"])
    np.testing.assert_array_equal(out.to_numpy(), expected)
    est = Derivatives().fit(frame)
    assert est.n_features_in_ == 3
    assert list(est.feature_names_in_) == ["trajectory", "t", "theta"]
    assert list(est.get_feature_names_out()) == ["theta", "theta_dot", "theta_ddot"]
    # transform is stateless, trajectory by trajectory: a subset gives the same rows
    part = frame[frame["trajectory"].isin([3, 7])]
    pd.testing.assert_frame_equal(est.transform(part), out.loc[part.index])


def test_transformer_on_arrays(pendulum):
    data, frame = pendulum
    full = Derivatives().fit_transform(frame).to_numpy()
    est = Derivatives(time=1, trajectory=0).fit(frame.to_numpy())
    np.testing.assert_array_equal(est.transform(frame.to_numpy()), full)
    assert list(est.get_feature_names_out()) == ["q0", "q0_dot", "q0_ddot"]
    names = est.get_feature_names_out(["trajectory", "t", "phi"])
    assert list(names) == ["phi", "phi_dot", "phi_ddot"]
    one = frame[frame["trajectory"] == 0]
    by_dt = Derivatives(time=None, dt=0.01, trajectory=None).fit_transform(
        one[["theta"]].to_numpy()
    )
    np.testing.assert_allclose(by_dt, full[: len(one)])
    pandas_out = Derivatives(time=1, trajectory=0).set_output(transform="pandas")
    out = pandas_out.fit_transform(frame.to_numpy())
    assert list(out.columns) == ["q0", "q0_dot", "q0_ddot"]


def test_transformer_angles_and_coordinates():
    t = np.arange(300) * 0.01
    theta = np.angle(np.exp(1j * (3.0 * t)))
    frame = pd.DataFrame({"time": t, "theta": theta, "x": 0.5 * t**2, "note": 1.0})
    est = Derivatives(
        time="time",
        trajectory=None,
        coordinates=["x", "theta"],
        angles=["theta"],
        method="savgol",
    )
    out = est.fit_transform(frame)
    assert list(out.columns) == [
        "x",
        "theta",
        "x_dot",
        "theta_dot",
        "x_ddot",
        "theta_ddot",
    ]
    assert est.angles_ == ["theta"]
    np.testing.assert_allclose(out["theta_dot"], 3.0, atol=1e-6)
    np.testing.assert_allclose(out["x_ddot"], 1.0, atol=1e-6)


@pytest.mark.parametrize(
    "params, X, match",
    [
        (
            {},
            pd.DataFrame({"trajectory": [0] * 20, "x": np.arange(20.0)}),
            "no time column 't'",
        ),
        (
            {"trajectory": "run"},
            pd.DataFrame({"t": np.arange(20.0), "x": 1.0}),
            "no trajectory column 'run'",
        ),
        (
            {"dt": 0.1},
            pd.DataFrame({"t": np.arange(20.0), "x": 1.0}),
            "not both: set time=None",
        ),
        ({"time": None, "trajectory": None}, np.ones((20, 2)), "time=None needs dt"),
        ({}, np.ones((20, 3)), "X is an array, so time must be a column index"),
        ({"time": 0, "trajectory": 5}, np.ones((20, 3)), "not a column index of X"),
        (
            {"trajectory": None},
            pd.DataFrame({"t": np.arange(20.0), "x": 1.0, "x_dot": 0.0}),
            "look like velocities or accelerations",
        ),
        (
            {"trajectory": None, "angles": ["y"]},
            pd.DataFrame({"t": np.arange(20.0), "x": 1.0}),
            "angles names 'y', which is not a coordinate",
        ),
        (
            {"method": "savgol", "window": 4},
            pd.DataFrame({"t": np.arange(20.0), "trajectory": 0, "x": 1.0}),
            "window must be an odd integer",
        ),
    ],
)
def test_transformer_layout_errors(params, X, match):
    with pytest.raises(ValueError, match=match):
        Derivatives(**params).fit(X)


def test_transformer_clone_pickle_and_params(pendulum):
    _, frame = pendulum
    est = Derivatives("savgol", window=21, angles=["theta"])
    assert clone(est).get_params() == est.get_params()
    fitted = est.fit(frame)
    again = pickle.loads(pickle.dumps(fitted))
    np.testing.assert_array_equal(again.transform(frame), fitted.transform(frame))
    with pytest.raises(ValueError, match="feature names should match"):
        fitted.transform(frame[["t", "trajectory", "theta"]])


def test_pipeline_with_lagrangian_sindy_under_group_kfold(pendulum):
    data, frame = pendulum
    lib = single_pendulum().paper_library()
    pipe = make_pipeline(Derivatives(angles=["theta"]), LagrangianSINDy(lib))
    scores = cross_val_score(
        pipe, frame, data.tau, cv=GroupKFold(5), groups=data.groups
    )
    assert np.all(scores > 0.97)
    model = pipe.fit(frame, data.tau)[-1]
    assert np.count_nonzero(model.coef_) == 2  # theta_dot**2 and cos(theta)
    # the same pipeline on raw finite differences: noise in q_ddot swamps the fit
    rough = make_pipeline(Derivatives("finite_difference"), LagrangianSINDy(lib))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rough_scores = cross_val_score(
            rough, frame, data.tau, cv=GroupKFold(5), groups=data.groups
        )
    assert rough_scores.mean() < 0.9


# Rows are samples of a trajectory in time order, so two generic checks cannot hold.
EXPECTED_FAILED_CHECKS = {
    "check_methods_sample_order_invariance": "rows are time samples: order matters",
    "check_methods_subset_invariance": "a single row is not a trajectory",
}


@parametrize_with_checks(
    [Derivatives(time=None, dt=0.1, trajectory=None)],
    expected_failed_checks=lambda est: EXPECTED_FAILED_CHECKS,
)
def test_sklearn_common_checks(estimator, check):
    check(estimator)


def test_pspline_float_jitter_in_time_stamps_takes_the_uniform_path():
    # Time stamps uniform to within 3e-7 of a step (float jitter, below the 1e-6
    # tolerance) give the derivatives of the exact grid, one trajectory or several
    # (they share the cached eigenbasis instead of taking the banded path).
    rng = np.random.default_rng(0)
    n = 400
    t = np.concatenate([np.arange(n) * 0.01 + 10.0 * g for g in range(3)])
    groups = np.repeat(np.arange(3), n)
    q = np.c_[np.sin(3 * t), np.cos(2 * t)] + 1e-3 * rng.normal(size=(3 * n, 2))
    jittered = t + 0.01 * 3e-7 * rng.uniform(-1, 1, size=t.size)
    for g in (None, groups):
        rows = slice(None) if g is not None else slice(0, n)
        exact = derivatives(q[rows], t[rows], groups=None if g is None else g)
        got = derivatives(q[rows], jittered[rows], groups=None if g is None else g)
        # the mean steps differ by ~1e-9: measured max relative difference ~1e-9
        np.testing.assert_allclose(got, exact, rtol=1e-7, atol=1e-7)


@pytest.mark.parametrize("n", [600, 2600, 4200])  # exact search; fast one at 4200
def test_banded_gcv_search_ends_near_the_grid_minimum(n):
    """The golden-section search over the lambda grid ends where GCV is within
    1e-3 of its smallest value on the grid (a scan of every point; measured: the
    grid minimum itself, or 4e-4 above it where GCV is flat between two points)."""
    from lagsindy.differentiation import _BandedPSpline

    rng = np.random.default_rng(0)
    t = np.sort(rng.uniform(0.0, n / 100.0, n))  # uneven stamps: the banded path
    q = np.c_[np.sin(2.0 * t), np.cos(0.7 * t) + 0.3 * np.sin(3.1 * t)]
    q += 1e-3 * rng.standard_normal(q.shape)
    spline = _BandedPSpline(t, 2)
    Bty = np.asarray(spline.B.T @ q)
    best, _ = spline.search(q, Bty)
    exact = np.stack(
        [spline.gcv(float(lam), q, Bty.astype(np.complex128)) for lam in spline.grid]
    )
    chosen = exact[best, [0, 1]]
    assert np.all(chosen <= exact.min(axis=0) * (1 + 1e-3)), (best, exact.argmin(0))
