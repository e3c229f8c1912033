"""The robot benchmark runs end to end at a tiny size (needs pinocchio)."""

import numpy as np
import pytest

import benchmarks._common as common

pytest.importorskip("pinocchio")


@pytest.mark.slow  # the 7-joint benchmark end to end (~30 s); the robot fits are tested in tests/robots
def test_robots_benchmark_tiny(tmp_path, monkeypatch):
    from benchmarks import robots

    monkeypatch.setenv("LAGSINDY_BENCH_TINY", "1")
    monkeypatch.setattr(common, "RESULTS", tmp_path)
    assert robots.main(["--quick"]) == 0
    text = (tmp_path / "robots_quick.md").read_text()
    assert (
        "- command: `LAGSINDY_BENCH_TINY=1 python -m benchmarks.robots --quick`" in text
    )
    assert "77 parameters (70 link + 7 rotor) -> 48 base parameters" in text
    # both regressors give the same fit
    assert "The two regressors' fits agree to" in text


def test_simulated_torques_are_the_regressor_model():
    """robots_data's torques = lagsindy's regressor with the true parameters + extras."""
    from benchmarks.robots import friction_columns
    from benchmarks.robots_data import planar_arm
    from lagsindy import CandidateLibrary

    data = planar_arm(duration=0.2)
    lib = CandidateLibrary.from_urdf(data.urdf)
    truth = lib.nominal_.copy()
    truth[-2:] = data.armature
    tau = lib.euler_lagrange_columns(data.q_true, data.qd_true, data.qdd_true) @ truth
    tau += (
        friction_columns(data.qd_true) @ np.r_[data.viscous, data.coulomb, data.offset]
    )
    np.testing.assert_allclose(tau, data.tau_true, rtol=0, atol=1e-10)
