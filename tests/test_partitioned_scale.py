"""The scale benchmark's data writer (``benchmarks/scale.py``) is right.

The 1e8-row benchmark simulates its forced double pendulums with a batched
fixed-step DOP853 in numpy instead of :func:`lagsindy.systems.make_dataset`'s
adaptive solver (16x less CPU time); these tests hold it to the system's own
dynamics, a tight reference solution and the old writer's trajectories, and check
that fits of the files it writes find the true Lagrangian, partitioned as in memory.
"""

import math
import warnings

import numpy as np
import pandas as pd
import pytest

from benchmarks import scale
from lagsindy import LagrangianSINDy
from lagsindy.systems import double_pendulum, make_dataset

SYSTEM = double_pendulum()


def test_closed_form_dynamics_are_the_systems():
    rng = np.random.default_rng(0)
    q = rng.uniform(-math.pi, math.pi, (500, 2))
    qd = rng.uniform(-8, 8, (500, 2))
    tau = rng.uniform(-2, 2, (500, 2))
    a1, a2 = scale.accelerations(*q.T, *qd.T, *tau.T)
    want = SYSTEM.forward_dynamics(q, qd, tau)
    # measured 1.1e-13 (rounding)
    np.testing.assert_allclose(np.c_[a1, a2], want, rtol=0, atol=1e-12)


def test_forces_are_make_datasets():
    data = make_dataset(SYSTEM, n_trajectories=3, duration=1.0, random_state=4)
    t = data.t
    omega = np.repeat(data.omega, t.size // 3)
    got = scale.paper_forces(t, omega, np.asarray(SYSTEM.input_matrix, float))
    np.testing.assert_allclose(np.stack(got, axis=1), data.tau, rtol=0, atol=1e-15)


def test_batched_simulation_is_near_a_tight_reference():
    n, rate = 6, scale.RATE
    x0, omega = scale.file_draws(SYSTEM, 0)
    x0, omega = x0[:n], omega[:n]
    t = np.arange(int(rate)) / rate  # 1 s
    B = np.asarray(SYSTEM.input_matrix, float)
    got = scale.simulate_batch(x0, omega, t, B).transpose(2, 0, 1)
    ref = np.stack(
        [
            SYSTEM.simulate(
                x0[k],
                t,
                lambda tt, _x, k=k: SYSTEM.paper_input(tt, omega[k : k + 1])[0],
                rtol=1e-13,
                atol=1e-13,
            )
            for k in range(n)
        ]
    )
    # The old writer: make_dataset's adaptive DOP853 (rtol = atol = 1e-9) on the
    # same draws (the file's first n of 100 trajectories: same x0 and omega).
    old = make_dataset(
        SYSTEM, n_trajectories=scale.PER_FILE, duration=1.0, random_state=1000
    )
    old_states = old.X.reshape(scale.PER_FILE, t.size, 6)[:n, :, :4]
    np.testing.assert_array_equal(old_states[:, 0], x0)
    err = np.abs(got - ref).max()
    err_old = np.abs(old_states - ref).max()
    # measured: batched 4.8e-10, old 2.6e-8 from the reference over 1 s
    assert err < 5e-9, err
    assert err < err_old, (err, err_old)
    assert np.abs(got - old_states).max() < 2e-7


def _write(folder, monkeypatch, n_traj=30, n_samples=300):
    pytest.importorskip("pyarrow")  # lagsindy[dask]
    monkeypatch.setattr(scale, "PER_FILE", 10)
    monkeypatch.setattr(scale, "BATCH_FILES", 2)
    assert scale.write_data(folder, n_traj, n_samples) == n_traj * n_samples
    assert scale.write_data(folder, n_traj, n_samples) == 0  # kept, not rewritten
    return folder


def _read(folder):
    files = sorted(folder.glob("part-*.parquet"))
    return [pd.read_parquet(f) for f in files]


def test_written_files_are_deterministic_whole_trajectories(tmp_path, monkeypatch):
    parts = _read(_write(tmp_path / "a", monkeypatch))
    again = _read(_write(tmp_path / "b", monkeypatch, n_traj=20))  # a prefix
    assert len(parts) == 3 and len(again) == 2
    for a, b in zip(parts, again):  # batches of 2 files: the same numbers
        pd.testing.assert_frame_equal(a, b)
    for k, part in enumerate(parts):
        labels = part["trajectory"].to_numpy()
        assert np.array_equal(np.unique(labels), np.arange(10 * k, 10 * k + 10))
        x0, _ = scale.file_draws(SYSTEM, k)
        first = part.groupby("trajectory").head(1)
        cols = ["theta1", "theta2", "theta1_dot", "theta2_dot"]
        np.testing.assert_array_equal(first[cols].to_numpy(), x0)


def test_fits_of_the_written_files(tmp_path, monkeypatch):
    parts = _read(_write(tmp_path, monkeypatch))
    frame = pd.concat(parts, ignore_index=True)
    tau_cols = ["tau_theta1", "tau_theta2"]
    X = frame.drop(columns=["trajectory", *tau_cols])
    library = SYSTEM.paper_library()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        memory = LagrangianSINDy(library, formulation="strong").fit(
            X, frame[tau_cols].to_numpy(), groups=frame["trajectory"].to_numpy()
        )
        chunks = LagrangianSINDy(library, formulation="strong").fit(parts)
    true = SYSTEM.true_coefficients(memory.library_)
    coef = memory.coef_.ravel()
    # the true Lagrangian; measured 3e-9 relative (integration error)
    assert np.abs(coef - true).max() / np.abs(true).max() < 1e-7
    got = np.abs(chunks.coef_ - memory.coef_).max() / np.abs(coef).max()
    # measured 2.8e-12: rounding of the summation order (the in-memory fit of the
    # files in reverse order moves them by 6.6e-12 from the in-memory fit; the
    # double pendulum's 63-term Gram matrix is far worse conditioned than the
    # single pendulum's of tests/test_partitioned.py, held to 1e-12)
    assert got < 1.5e-11, got


def test_report_rows(monkeypatch):
    base = {"mode": "memory", "rows": 100, "seconds": 2.0, "peak_mib": 10.0}
    results = {
        "memory-small": {
            **base,
            "coef": [1.0, 2.0],
            "equation": "L = a",
            "load_before": 3.0,
            "load_after": 4.0,
        },
        "dask1-small": {
            **base,
            "mode": "dask",
            "workers": 1,
            "seconds": 4.0,
            "coef": [1.0, 2.0 + 2e-12],
            "equation": "L = b",
            "cluster_seconds": 7.0,
            "load_before": 5.0,
            "load_after": 6.0,
        },
        "_data": {"seconds": 12.0, "rows": 100},
        "dask1-large": {
            "mode": "dask",
            "workers": 1,
            "files": 20,
            "error": "exit -15",
            "rows_per_file": 50,
            "progress": {
                "seconds": 10.0,
                "partitions_done": 4,
                "peak_mib": 20.0,
                "load": 9.0,
            },
        },
    }
    _, _, runs = scale.plan(full=False)
    text = scale.report(results, runs, None, 10)
    assert (
        "| in memory | 100 | 2.0 s | 50 | 100% | 10 MiB | 0.0e+00 | - | 3.0 / 4.0 |"
        in text
    )
    row = "| Dask, 1 worker(s) | 100 | 4.0 s | 25 | 50% | 10 MiB | 1.0e-12 | 7 s |"
    assert row + " 5.0 / 6.0 |" in text
    assert "simulated and written in 12 s" in text
    # a stopped run: the rows of the partitions it finished, over its time
    stopped = "| Dask, 1 worker(s), stopped | 200 of 1,000 | 10.0 s | 20 | 40% |"
    assert stopped + " 20 MiB | - | - | - / 9.0 |" in text
