"""diagnose's per-joint input delay ("joint_delay"): a delay per driven joint,
estimated, kept when significant and when it predicts held-out data better, applied
per column in the model it returns."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from _robot_fit_data import planar_data

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy, diagnose
from lagsindy.delay import shift_input
from lagsindy.robots import FRICTION_KINDS, ROBOT_CATALOGUE, example_urdf, multisine

CATALOGUE = ["joint_delay", "viscous", "coulomb", "bias"]


def _delayed_planar(delays, noise=0.01, duration=6.0):
    """The two-link arm at 1 kHz, each joint's torque recorded ``delays`` (s)
    before it acts, 1 % torque noise."""
    data = planar_data(duration=duration, dt=0.001)
    # recorded(t) = acting(t + delay)
    tau = shift_input(data.tau, data.t, -np.asarray(delays))
    rng = np.random.default_rng(1)
    tau = tau + noise * tau.std(0) * rng.standard_normal(tau.shape)
    return data, tau


def _diagnosed(data, tau, catalogue=CATALOGUE):
    lib = CandidateLibrary.from_urdf(example_urdf("planar2"))
    est = LagrangianSINDy(
        lib, dissipation=DissipationLibrary(list(FRICTION_KINDS)), formulation="strong"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fit warns: it misses the delay
        est.fit(data.X, tau)
        return diagnose(est, data.X, tau, catalogue=catalogue)


@pytest.fixture(scope="module")
def delayed():
    """Shoulder 4 ms, elbow 10 ms."""
    data, tau = _delayed_planar([0.004, 0.010])
    return data, tau, _diagnosed(data, tau)


def test_joint_delays_found_per_joint(delayed):
    data, tau, report = delayed
    # measured: 3.92 and 10.05 ms
    assert report.input_delays["shoulder"] == pytest.approx(0.004, abs=3e-4)
    assert report.input_delays["elbow"] == pytest.approx(0.010, abs=3e-4)
    assert report.effects[:2] == ["delay(shoulder)", "delay(elbow)"]
    step = report.steps[1]
    assert step.candidate.kind == "joint_delay"
    assert step.candidate.coordinates == ("elbow",)
    assert step.coefficient == pytest.approx(10.0, abs=0.3)  # ms
    assert "input delay of one joint" in str(report)
    assert "ms (+-" in step.units


def test_the_final_model_is_fitted_on_the_input_shifted_per_joint(delayed):
    data, tau, report = delayed
    acting = report.shift_input(tau, data.t)
    expected = shift_input(
        tau,
        data.t,
        [report.input_delays["shoulder"], report.input_delays["elbow"]],
        method="fourier",
    )
    np.testing.assert_array_equal(acting, expected)
    # the final model explains the shifted input to the noise (1 % of the torque
    # RMS; measured residual/noise 1.0 on the interior rows), not the recorded one
    # (measured 1.65 and 6.5 times the noise)
    inner = slice(50, -50)
    pred = report.final.predict(data.X)
    noise = 0.01 * tau.std(0)
    rms_shifted = np.sqrt(np.mean((acting - pred)[inner] ** 2, axis=0))
    rms_recorded = np.sqrt(np.mean((tau - pred)[inner] ** 2, axis=0))
    assert np.all(rms_shifted < 1.3 * noise)
    assert np.all(rms_recorded > 1.4 * noise)
    # friction within 2 % once the delays are applied (measured 0.1 %)
    coef = dict(
        zip(
            [f.name for f in report.final.dissipation_terms_],
            report.final.dissipation_coef_,
        )
    )
    assert coef["viscous(shoulder)"] == pytest.approx(0.6, rel=0.02)
    assert coef["viscous(elbow)"] == pytest.approx(0.3, rel=0.02)


def test_no_joint_delay_on_a_delay_free_arm():
    data, tau = _delayed_planar([0.0, 0.0])
    report = _diagnosed(data, tau)
    assert report.input_delays == {}
    assert not [e for e in report.effects if e.startswith("delay")]
    np.testing.assert_array_equal(report.shift_input(tau, data.t), tau)


@pytest.mark.slow  # one joint of two (the per-joint pruning has its own test)
def test_one_delayed_joint_only():
    """0 and 8 ms: only the elbow's delay is proposed (the shoulder's estimate,
    -0.27 +- 0.11 ms, is below half a sample)."""
    data, tau = _delayed_planar([0.0, 0.008])
    report = _diagnosed(data, tau)
    assert set(report.input_delays) == {"elbow"}
    assert report.input_delays["elbow"] == pytest.approx(0.008, abs=5e-4)  # 8.16


def test_a_spurious_joint_delay_is_pruned(monkeypatch):
    """A delay the estimate calls significant but that does not improve the
    held-out criterion (here: a 0.6 ms shoulder delay planted beside the real 8 ms
    elbow delay) is dropped; the real one stays."""
    from lagsindy.diagnostics import joint_delay

    real = joint_delay.estimate_joint_delays

    def planted(*args, **kwargs):
        estimate = real(*args, **kwargs)
        estimate.delays[0], estimate.std[0] = 6e-4, 1e-5
        estimate.left_out[:, 0] = 6e-4
        return estimate

    monkeypatch.setattr(joint_delay, "estimate_joint_delays", planted)
    data, tau = _delayed_planar([0.0, 0.008])
    report = _diagnosed(data, tau)
    assert set(report.input_delays) == {"elbow"}
    assert "delay(shoulder)" not in report.effects


@pytest.mark.slow  # a catalogue precedence rule
def test_joint_delay_replaces_the_single_delay_when_both_are_named(delayed):
    data, tau, _ = delayed
    report = _diagnosed(data, tau, catalogue=["delay", *CATALOGUE])
    assert "delay" not in report.effects
    assert set(report.input_delays) == {"shoulder", "elbow"}


def test_significance_boundaries():
    """Kept: at least half a sampling interval and more than twice the standard
    error (the single delay's rule, with half a sample for its tenth)."""
    from lagsindy.diagnostics.joint_delay import JointDelayEstimate

    dt = 1e-3

    def estimate(delay, std, driven=True):
        return JointDelayEstimate(
            np.array([delay]),
            np.array([std]),
            np.array([driven]),
            ["q"],
            np.array([-dt, 0, dt]),
            np.zeros((3, 1)),
            dt,
        )

    assert not estimate(0.499 * dt, 1e-9).significant()[0]
    assert estimate(0.501 * dt, 1e-9).significant()[0]
    assert not estimate(-0.499 * dt, 1e-9).significant()[0]
    assert estimate(-0.501 * dt, 1e-9).significant()[0]
    assert not estimate(1e-3, 0.5001e-3).significant()[0]
    assert estimate(1e-3, 0.4999e-3).significant()[0]
    assert not estimate(1e-3, 1e-9, driven=False).significant()[0]
    assert estimate(1e-3, 1e-9).kept()[0] == 1e-3
    assert estimate(4e-4, 1e-9).kept()[0] == 0.0


def test_robot_catalogue_names_the_per_joint_delay():
    assert "joint_delay" in ROBOT_CATALOGUE
    assert "delay" not in ROBOT_CATALOGUE


# ------------------------------------------------------------- a 7-joint arm
def _arm7(delays, duration=6.0, seed=0):
    lib = CandidateLibrary.from_urdf(
        example_urdf("arm7"), [f"joint{i}" for i in range(1, 8)]
    )
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 0.001)
    d = 7
    q, qd, qdd = multisine(t, d, (0.9, 2.1, 3.7), (0.15, 0.35), random_state=rng)
    truth = lib.nominal_.copy()
    truth[-d:] = 0.05
    tau = lib.euler_lagrange_columns(q, qd, qdd) @ truth
    tau += np.linspace(0.5, 0.2, d) * qd + np.linspace(0.4, 0.1, d) * np.tanh(qd / 0.01)
    tau += 0.05
    tau = shift_input(tau, t, -np.asarray(delays))
    tau += 0.01 * tau.std(0) * rng.standard_normal(tau.shape)
    X = np.hstack([q, qd, qdd])
    est = LagrangianSINDy(
        lib, dissipation=DissipationLibrary(list(FRICTION_KINDS)), formulation="strong"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(X, tau)
        return diagnose(est, X, tau, catalogue=CATALOGUE)


@pytest.mark.slow
def test_seven_joint_arm_delays():
    """4 ms on joint 2, 10 ms on joint 5, none elsewhere (about 2 minutes)."""
    delays = np.zeros(7)
    delays[[1, 4]] = [0.004, 0.010]
    report = _arm7(delays)
    assert set(report.input_delays) == {"joint2", "joint5"}
    # measured 4.07 +- 0.02 and 9.30 +- 0.52 ms (10.03 with the spring kind among
    # the candidates); issue #42 asks for 1 ms
    assert report.input_delays["joint2"] == pytest.approx(0.004, abs=3e-4)
    assert report.input_delays["joint5"] == pytest.approx(0.010, abs=1e-3)


@pytest.mark.slow
def test_seven_joint_arm_without_delays():
    """Estimates of a fraction of a millisecond on some joints pass the
    significance test (joint 6: -0.81 ms) but not the held-out ones."""
    report = _arm7(np.zeros(7))
    assert report.input_delays == {}
