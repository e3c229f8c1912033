"""``lagsindy simulate`` and ``simulate-model``."""

import numpy as np
import pandas as pd

from lagsindy import LagrangianSINDy

from ._helpers import run


def test_simulate_writes_the_documented_columns(workdir):
    df = pd.read_csv(workdir / "data.csv")
    assert list(df.columns) == [
        "trajectory",
        "t",
        "x",
        "theta",
        "x_dot",
        "theta_dot",
        "x_ddot",
        "theta_ddot",
        "tau_x",
        "tau_theta",
    ]
    assert df.trajectory.nunique() == 6 and len(df) == 6 * 400
    assert list(pd.read_csv(workdir / "q.csv").columns) == [
        "trajectory",
        "t",
        "x",
        "theta",
        "tau_x",
        "tau_theta",
    ]


def test_simulate_model_from_initial_states(capsys, workdir, tmp_path):
    out_csv = tmp_path / "traj.csv"
    code, _, err = run(
        capsys,
        "simulate-model",
        workdir / "model.json",
        "--x0",
        "0,1,0,0",
        "--x0",
        "0,0.5,0,0",
        "--duration",
        "1",
        "--out",
        out_csv,
    )
    assert code == 0, err
    traj = pd.read_csv(out_csv)
    assert traj.trajectory.nunique() == 2 and len(traj) == 2 * 101
    est = LagrangianSINDy.load(workdir / "model.json")
    states = est.simulate([0, 1, 0, 0], np.arange(101) / 100)
    first = traj[traj.trajectory == 0]
    np.testing.assert_allclose(
        first[["x", "theta", "x_dot", "theta_dot"]], states, atol=1e-9
    )
    # the same through "simulate --model"
    code, _, err = run(
        capsys,
        "simulate",
        "--model",
        workdir / "model.json",
        "--x0",
        "0,1,0,0",
        "--duration",
        "1",
        "--out",
        tmp_path / "t2.csv",
    )
    assert code == 0, err
    np.testing.assert_allclose(
        pd.read_csv(tmp_path / "t2.csv").to_numpy(), first.to_numpy(), atol=1e-9
    )


def test_system_names_in_help_match_the_systems():
    from lagsindy.cli import SYSTEM_NAMES
    from lagsindy.systems import SYSTEMS

    assert list(SYSTEM_NAMES) == sorted(SYSTEMS)
