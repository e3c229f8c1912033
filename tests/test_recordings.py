"""Recordings (#13): long records, gaps, timing glitches, shipped data, CLI angles."""

import re
import warnings

import numpy as np
import pandas as pd
import pytest

from lagsindy.cli import main
from lagsindy.differentiation import derivatives, split_gaps
from lagsindy.io import (
    find_multiarm_pendulum,
    load_multiarm_parameters,
    load_multiarm_pendulum,
)


def rel_rms(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2) / np.mean(b**2)))


def inner_rows(groups, n, edge):
    """Rows at least ``edge`` samples from both ends of their trajectory."""
    g = np.zeros(n, dtype=int) if groups is None else np.asarray(groups)
    first = np.r_[0, np.flatnonzero(np.diff(g)) + 1]
    last = np.r_[first[1:], n]
    inner = np.zeros(n, dtype=bool)
    for a, b in zip(first, last):
        inner[a + edge : b - edge] = True
    return inner


# ----------------------------------------------------------------- long records
def test_long_record_keeps_full_bandwidth_whole_and_grouped():
    # 30 s at 1 kHz with 12 Hz and 25 Hz content: the old 500-span cap left 99 %
    # error on the whole record (knots every 60 samples cannot follow 25 Hz).
    t = np.arange(30001) / 1000.0
    w1, w2 = 2 * np.pi * 12, 2 * np.pi * 25
    noise = 1e-5 * np.random.default_rng(0).normal(size=t.size)
    q = np.sin(w1 * t) + 0.2 * np.sin(w2 * t) + noise
    qdd = -(w1**2) * np.sin(w1 * t) - 0.2 * w2**2 * np.sin(w2 * t)
    groups = np.minimum(t.astype(int), 29)  # 1 s pieces
    whole = derivatives(q, t)
    pieces = derivatives(q, t, groups=groups)
    inner_whole = inner_rows(None, t.size, 20)
    inner_pieces = inner_rows(groups, t.size, 20)
    # measured 0.020 % whole, 0.036 % grouped
    assert rel_rms(whole[inner_whole, 2], qdd[inner_whole]) < 1e-3
    assert rel_rms(pieces[inner_pieces, 2], qdd[inner_pieces]) < 1e-3
    # the two agree away from the piece ends (measured 0.03 %)
    assert rel_rms(whole[inner_pieces, 2], pieces[inner_pieces, 2]) < 1e-3


def test_banded_path_gives_the_eigenbasis_gcv():
    # the O(n) path (complex-step trace) scores lambda exactly as the
    # Demmler-Reinsch eigenbasis does (measured agreement ~1e-8 relative)
    from lagsindy import differentiation as d

    t = np.arange(401) / 100.0
    rng = np.random.default_rng(3)
    q = np.c_[np.sin(3 * t), np.cos(5 * t)] + 1e-3 * rng.normal(size=(401, 2))
    for order in (3, 4):
        dense = d._PSpline(t, order)
        banded = d._BandedPSpline(t, order)
        Bty = dense.B.T @ q
        z = d.solve_triangular(dense.L, Bty, lower=True)
        b = dense.U.T @ z
        c0 = d.solve_triangular(dense.L, z, lower=True, trans="T")
        rss0 = np.sum((q - dense.B @ c0) ** 2, axis=0)
        for i in (10, 60, 120):
            lam = dense.grid[i]
            rss = rss0 + (dense.shrink[i] ** 2) @ (b**2)
            expected = dense.n * rss / (dense.n - dense.edf[i]) ** 2
            got = banded.gcv(lam, q, (banded.B.T @ q).astype(complex))
            np.testing.assert_allclose(got, expected, rtol=1e-6)


# ----------------------------------------------------------------- gaps
def gappy_record():
    """6 s at 1 kHz with three 0.19 s gaps; the motion after each gap has another
    phase (the recorder lost what happened in between)."""
    t = np.arange(0, 6, 0.001)
    keep = np.ones(t.size, dtype=bool)
    for a in (1.5, 3.0, 4.5):
        keep &= ~((t > a) & (t < a + 0.19))
    t = t[keep]
    phase = np.array([0.0, 2.0, 4.0, 1.0])[np.searchsorted([1.5, 3.0, 4.5], t)]
    w1, w2 = 2 * np.pi * 1.1, 2 * np.pi * 2.3
    noise = 1e-4 * np.random.default_rng(0).normal(size=t.size)
    q = np.sin(w1 * t + phase) + 0.4 * np.sin(w2 * t) + noise
    qdd = -(w1**2) * np.sin(w1 * t + phase) - 0.4 * w2**2 * np.sin(w2 * t)
    return t, q, qdd


def test_gaps_split_the_record_with_one_warning():
    t, q, qdd = gappy_record()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        X, groups = derivatives(q, t, return_groups=True)
    messages = [str(w.message) for w in caught]
    assert len(messages) == 1
    assert "3 gap(s)" in messages[0] and "split_gaps" in messages[0]
    assert "t = 1.69" in messages[0]  # says where
    assert np.unique(groups).tolist() == [0, 1, 2, 3]
    np.testing.assert_array_equal(split_gaps(t), groups)
    gap_rows = np.flatnonzero(np.diff(t) > 0.01)
    near = np.zeros(t.size, dtype=bool)
    for i in gap_rows:
        near[i - 50 : i + 51] = True
    assert rel_rms(X[near, 2], qdd[near]) < 0.05  # measured 1.8 %
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bridged = derivatives(q, t, gap_factor=None)
    assert rel_rms(bridged[near, 2], qdd[near]) > 0.08  # measured 12 %


def test_split_gaps_per_trajectory_and_transformer():
    from lagsindy import Derivatives

    t = np.r_[np.arange(20), np.arange(30, 50), np.arange(20)] * 0.01
    groups = np.repeat(["a", "b"], [40, 20])
    assert split_gaps(t, groups).tolist() == [0] * 20 + [1] * 20 + [2] * 20
    frame = pd.DataFrame({"trajectory": groups, "t": t, "x": np.sin(t)})
    with pytest.warns(UserWarning, match="1 gap"):
        out = Derivatives().fit_transform(frame)
    assert np.allclose(out["x_ddot"], -np.sin(t), atol=1e-3)
    with pytest.raises(ValueError, match="gap_factor"):
        split_gaps(t, groups, gap_factor=0.5)


def test_weak_form_refuses_a_trajectory_with_a_gap():
    from lagsindy import LagrangianSINDy
    from lagsindy.systems import make_dataset, single_pendulum

    system = single_pendulum()
    data = make_dataset(system, n_trajectories=2, duration=4.0, random_state=1)
    keep = np.ones(len(data.t), dtype=bool)
    keep[150:170] = False  # 0.2 s lost in the first trajectory
    X, tau, t, groups = data.X[keep], data.tau[keep], data.t[keep], data.groups[keep]
    est = LagrangianSINDy(system.paper_library(), formulation="weak")
    with pytest.raises(ValueError, match="jumps between rows 149 and 150") as info:
        est.fit(X, tau, groups=groups)
    assert "wrapped" not in str(info.value)  # a gap, not a wrap
    est.fit(X, tau, groups=split_gaps(t, groups))  # the segments fit
    table = est.coef_table().set_index("term")["coefficient"]
    assert table["cos(theta)"] == pytest.approx(9.81, rel=0.01)


def test_timing_glitches_are_reported_by_row():
    t = np.arange(200) * 0.015
    t[[50, 120]] = t[[49, 119]] + 0.002  # frames 2 ms after the previous one
    q = np.sin(2 * t)
    with pytest.warns(UserWarning, match=r"2 row\(s\).*50 \(t = .*120 \(t = "):
        derivatives(q, t)


def test_dropped_samples_are_reported_and_split_gaps_cuts_there():
    """Single dropped frames (steps of 2 dt, below the gap factor of 5) bias the weak
    form, which assumes evenly spaced samples; derivatives() now says so."""
    t = np.delete(np.arange(400) * 0.01, [100, 250])
    q = np.sin(2 * t)
    with pytest.warns(UserWarning, match=r"2 step\(s\).*before row\(s\) 100 .*249 "):
        derivatives(q, t)
    labels = split_gaps(t, gap_factor=1.5)  # the advice
    assert np.flatnonzero(np.diff(labels) != 0).tolist() == [99, 248]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        regular = np.arange(400) * 0.01
        derivatives(np.sin(2 * regular), regular)  # a regular clock: nothing to say
        jitter = np.random.default_rng(0).uniform(-0.3, 0.3, 400) * 0.01
        uneven = regular + jitter  # truthful uneven stamps (positions taken then)
        derivatives(np.sin(2 * uneven), uneven)  # no regular clock
    # (positions on the even clock stamped with that jitter: the stamps disagree
    # with the motion and the clock is rebuilt, tests/test_clocks.py)


# ----------------------------------------------------------------- shipped data
def test_shipped_recordings_load_without_configuration(monkeypatch):
    monkeypatch.delenv("LAGSINDY_MULTIARM_DIR", raising=False)
    folder = find_multiarm_pendulum()
    assert folder.parts[-3:] == ("lagsindy", "data", "multiarm_pendulum")
    assert (folder / "LICENSE").is_file() and (folder / "README.md").is_file()
    triple = load_multiarm_pendulum(which="triple")
    assert triple.trajectory.nunique() == 22
    assert [c for c in triple.columns if c.startswith("theta") and "dot" not in c] == [
        "theta1",
        "theta2",
        "theta3",
    ]
    assert np.all(np.diff(triple.t) > 0)
    assert load_multiarm_pendulum(which="triple", split="vad").trajectory.nunique() == 4
    params = load_multiarm_parameters("triple")
    assert list(params)[:3] == ["m1", "m2", "m3"] and len(params) == 15
    assert params["g"] == pytest.approx(9.808, abs=1e-3)
    assert params["L2"] == pytest.approx(0.2287)
    single = load_multiarm_parameters("single")
    assert list(single) == ["a1", "m1", "I1", "k1", "g"]


def test_environment_variable_still_overrides(tmp_path, monkeypatch):
    monkeypatch.setenv("LAGSINDY_MULTIARM_DIR", str(tmp_path))
    assert find_multiarm_pendulum() == tmp_path
    with pytest.raises(FileNotFoundError, match="path=None"):
        load_multiarm_parameters("double")


# ----------------------------------------------------------------- CLI angles
def test_cli_unwraps_angles_as_the_api_does(tmp_path, capsys):
    from lagsindy.systems import make_dataset, single_pendulum

    data = make_dataset(
        single_pendulum(), n_trajectories=4, duration=3.0, random_state=0
    )
    frame = data.to_frame()
    theta = frame["theta"].to_numpy() + np.pi  # pi = hanging down, as cameras give
    wrapped = np.angle(np.exp(1j * theta))
    assert np.abs(np.diff(wrapped)).max() > 5  # really wrapped
    base = frame[["trajectory", "t", "tau_theta"]].copy()
    models = []
    for name, values in (("unwrapped", theta), ("wrapped", wrapped)):
        base.assign(theta=values).to_csv(tmp_path / f"{name}.csv", index=False)
        code = main(
            [
                "fit",
                str(tmp_path / f"{name}.csv"),
                "--coordinates",
                "theta",
                "--angles",
                "theta",
                "--formulation",
                "strong",
                "--out",
                str(tmp_path / f"{name}.json"),
                "--quiet",
            ]
        )
        assert code == 0, capsys.readouterr().err
        models.append(capsys.readouterr().out.strip())
    assert models[0] == models[1]
    assert "cos(theta)" in models[0]


def test_cli_fits_the_segments_of_a_record_with_a_gap(tmp_path, capsys):
    from lagsindy.systems import make_dataset, single_pendulum

    data = make_dataset(
        single_pendulum(), n_trajectories=2, duration=4.0, random_state=1
    )
    frame = data.to_frame()[["trajectory", "t", "theta", "tau_theta"]]
    frame = frame.drop(index=range(150, 170))  # 0.2 s lost in trajectory 0
    frame.to_csv(tmp_path / "gap.csv", index=False)
    args = [
        "fit",
        str(tmp_path / "gap.csv"),
        "--coordinates",
        "theta",
        "--angles",
        "theta",
        "--formulation",
        "weak",
        "--out",
        str(tmp_path / "m.json"),
        "--quiet",
    ]
    code = main(args)
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert re.search(r"1 gap\(s\).*row\(s\) 150 .*uses these segments", captured.err)
    # without the segments the weak form would refuse (it integrates over rows)
    assert "cos(theta)" in captured.out


def test_banded_fast_trace_matches_the_exact_one():
    # records of more than _PSPLINE_FD_MIN coefficients score lambda with a real
    # one-sided difference of Cholesky log-determinants; against the complex-step
    # trace: measured relative GCV differences <= 6e-7 at lambda * s_max <= 1e9
    from lagsindy import differentiation as d

    t = np.arange(6001) / 1000.0
    rng = np.random.default_rng(5)
    q = np.c_[np.sin(20 * t), np.cos(7 * t)] + 1e-3 * rng.normal(size=(t.size, 2))
    for order in (3, 4):
        banded = d._BandedPSpline(t, order)
        assert banded.nb > d._PSPLINE_FD_MIN
        Bty = np.asarray(banded.B.T @ q)
        for kappa in (1e-2, 1e2, 1e6):
            lam = kappa / banded.s_max
            exact = banded.gcv(lam, q, Bty.astype(complex))
            np.testing.assert_allclose(banded.gcv_fast(lam, q, Bty), exact, rtol=5e-6)


def _wrapped_pendulum():
    """A driven pendulum that turns over (theta reaches 15 rad), wrapped to
    (-pi, pi] as an encoder or atan2 reports it."""
    from lagsindy.systems import make_dataset, single_pendulum

    data = make_dataset(
        single_pendulum(), n_trajectories=10, duration=5.0, excitation="sincos",
        random_state=0,
    )  # fmt: skip
    q = (data.X[:, :1] + np.pi) % (2 * np.pi) - np.pi
    return data, q


def test_wrapped_angles_are_reported_by_derivatives():
    data, q = _wrapped_pendulum()
    # Within the trajectories theta wraps twice (rows 4197 and 4359 of trajectory
    # 8); the jump at row 4000 is the start of trajectory 8.
    with pytest.warns(UserWarning, match=r"\[0\] look like wrapped angles") as rec:
        derivatives(q, data.t, groups=data.groups)
    message = str(rec[0].message)
    assert (
        "2 time(s), before row(s) 4197 (t = 1.97), 4359" in message
        and "(angles=[0])" in message
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        X = derivatives(q, data.t, groups=data.groups, angles=[0])  # unwrapped
        # Unwrapped, the positions are the simulated ones again (to 1e-4 rad).
        assert np.abs(X[:, 0] - data.X[:, 0]).max() < 1e-4
        # One turn of range is not enough: the jump must be inside a trajectory.
        t = np.arange(len(q)) * 0.01
        labels = np.arange(len(q)) // 4197
        derivatives(np.where(labels[:, None] == 0, 0.1, 2 * np.pi - 0.1), t,
                    groups=labels)  # fmt: skip
        # A coordinate that spans more than a turn jumps for another reason, as
        # does one whose jump less a turn is unlike its other steps (0.97 here).
        derivatives(np.where(labels[:, None] == 0, 0.0, 7.0), t)
        step = np.where(labels == 0, 0.1 * np.sin(t), 5.31 + 0.1 * np.sin(t))
        assert np.ptp(step) < 2 * np.pi
        derivatives(step[:, None], t)


def test_weak_form_names_a_wrapped_angle_where_it_jumps():
    from lagsindy import LagrangianSINDy
    from lagsindy.systems import single_pendulum

    data, q = _wrapped_pendulum()
    X = np.array(data.X)
    X[:, 0] = q[:, 0]  # the exact derivatives, of the continuous angle
    est = LagrangianSINDy(single_pendulum().paper_library(), formulation="weak")
    with pytest.raises(ValueError, match="jumps between rows 4196 and 4197") as info:
        est.fit(X, data.tau, groups=data.groups)
    assert "coordinate(s) [0] are angles" in str(info.value)
    assert "wrapped to (-pi, pi]" in str(info.value)
