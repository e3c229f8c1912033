"""The command line on real clocks (#40): --time, --gap-factor, recorder velocities,
uneven clocks put on an even clock before the fit."""

import numpy as np
import pandas as pd
import pytest

from ._helpers import TRUE_TERMS, kept, run

CART = ["--coordinates", "x,theta", "--angles", "theta"]


def test_the_time_column_is_named_with_time(capsys, workdir, tmp_path):
    df = pd.read_csv(workdir / "q.csv").rename(columns={"t": "stamp"})
    df.to_csv(tmp_path / "renamed.csv", index=False)
    code, out, err = run(
        capsys, "fit", tmp_path / "renamed.csv", *CART, "--time", "stamp",
        "--held-out", "0", "--out", tmp_path / "m.json",
    )  # fmt: skip
    assert code == 0, err
    assert kept(tmp_path / "m.json") == TRUE_TERMS
    code, _, err = run(
        capsys, "fit", tmp_path / "renamed.csv", *CART, "--out", tmp_path / "n.json"
    )
    assert code == 2 and "name it with --time COLUMN" in err


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_clock_options_are_checked_before_the_data(
    capsys, workdir, tmp_path, no_derivatives, command
):
    out = ["--out" if command == "fit" else "--plot", tmp_path / "m.png"]
    code, _, err = run(
        capsys, command, workdir / "q.csv", *CART, "--time", "nosuch", *out
    )
    assert code == 2 and "nosuch" in err
    code, _, err = run(
        capsys, command, workdir / "q.csv", *CART, "--gap-factor", "1", *out
    )
    assert code == 2 and "--gap-factor must be a number > 1" in err


def test_predict_checks_the_gap_factor(capsys, workdir, tmp_path):
    code, _, err = run(
        capsys, "predict", workdir / "model.json", workdir / "q.csv",
        "--gap-factor", "0.5", "--out", tmp_path / "p.csv",
    )  # fmt: skip
    assert code == 2 and "--gap-factor must be a number > 1" in err


def test_predict_names_the_time_column(capsys, workdir, tmp_path):
    df = pd.read_csv(workdir / "q.csv").rename(columns={"t": "stamp"})
    df.to_csv(tmp_path / "renamed.csv", index=False)
    code, _, err = run(
        capsys, "predict", workdir / "model.json", tmp_path / "renamed.csv",
        "--time", "stamp", "--out", tmp_path / "p.csv",
    )  # fmt: skip
    assert code == 0, err
    assert list(pd.read_csv(tmp_path / "p.csv").columns[:2]) == ["trajectory", "stamp"]


def test_an_uneven_clock_is_put_on_an_even_clock_and_said(capsys, workdir, tmp_path):
    df = pd.read_csv(workdir / "q.csv")
    rng = np.random.default_rng(0)
    step = float(np.median(np.diff(df["t"][df["trajectory"] == 0])))
    df["t"] = df["t"] + rng.uniform(-0.2, 0.2, len(df)) * step  # 20 % jitter
    df = df[rng.random(len(df)) >= 0.05]  # 5 % of the frames dropped
    df.to_csv(tmp_path / "uneven.csv", index=False)
    code, out, err = run(
        capsys, "fit", tmp_path / "uneven.csv", *CART, "--held-out", "0",
        "--out", tmp_path / "m.json",
    )  # fmt: skip
    assert code == 0, err
    assert "segment(s) put on an even clock of dt = " in out
    assert kept(tmp_path / "m.json") == TRUE_TERMS


def test_recorded_velocities_are_used_and_said(capsys, workdir, tmp_path):
    df = pd.read_csv(workdir / "data.csv")
    df = df.drop(columns=["x_ddot", "theta_ddot"])
    df.to_csv(tmp_path / "v.csv", index=False)
    code, out, err = run(
        capsys, "fit", tmp_path / "v.csv", *CART, "--held-out", "0",
        "--out", tmp_path / "m.json",
    )  # fmt: skip
    assert code == 0, err
    assert "the recorded velocities ['x_dot', 'theta_dot'] used" in out
    assert "estimating accelerations of" in out
    assert kept(tmp_path / "m.json") == TRUE_TERMS
