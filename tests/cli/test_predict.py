"""``lagsindy predict`` and saved model files."""

import json

import numpy as np
import pandas as pd

from lagsindy import LagrangianSINDy

from ._helpers import kept, run


def test_predict_writes_forces_and_accelerations(capsys, workdir, tmp_path):
    out_csv = tmp_path / "pred.csv"
    code, out, err = run(
        capsys,
        "predict",
        workdir / "model.json",
        workdir / "data.csv",
        "--out",
        out_csv,
    )
    assert code == 0, err
    pred = pd.read_csv(out_csv)
    data = pd.read_csv(workdir / "data.csv")
    assert list(pred.columns) == [
        "trajectory",
        "t",
        "tau_x",
        "tau_theta",
        "x_ddot",
        "theta_ddot",
    ]
    est = LagrangianSINDy.load(workdir / "model.json")
    X = data[["x", "theta", "x_dot", "theta_dot", "x_ddot", "theta_ddot"]]
    np.testing.assert_allclose(
        pred[["tau_x", "tau_theta"]], est.predict(X), rtol=1e-9, atol=1e-9
    )
    r2 = float(out.split("R^2 of forces:")[1].split()[0])
    assert r2 > 0.999


def test_predict_takes_rows_in_any_order(capsys, workdir, tmp_path):
    """predict evaluates rows one by one: a 't' out of order is no error there."""
    df = pd.read_csv(workdir / "data.csv").iloc[::-1]
    df.to_csv(tmp_path / "reversed.csv", index=False)
    code, _, err = run(
        capsys, "predict", workdir / "model.json", tmp_path / "reversed.csv",
        "--out", tmp_path / "p.csv",
    )  # fmt: skip
    assert code == 0, err


def test_old_model_files_with_verbose_still_load(workdir, tmp_path):
    doc = json.loads((workdir / "model.json").read_text())
    doc["hyperparameters"]["verbose"] = 1  # as written by lagsindy 0.1
    old = tmp_path / "old.json"
    old.write_text(json.dumps(doc))
    est = LagrangianSINDy.load(old)
    assert est.verbose == 0
    assert kept(old) == kept(workdir / "model.json")
