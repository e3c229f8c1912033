"""``lagsindy fit``: data -> model, its scores, warnings and options."""

import json
import re
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from lagsindy import LagrangianSINDy

from ._helpers import ENV, PENDULUM, TRUE_TERMS, kept, pendulum_csv, run


def test_fit_recovers_the_structure_and_saves_a_model(workdir):
    assert kept(workdir / "model.json") == TRUE_TERMS
    doc = json.loads((workdir / "model.json").read_text())
    assert doc["coordinates"] == ["x", "theta"] and doc["case"] == "forces"


def test_fit_from_positions_only_estimates_derivatives(capsys, workdir, tmp_path):
    code, out, err = run(
        capsys,
        "fit",
        workdir / "q.csv",
        "--coordinates",
        "x,theta",
        "--angles",
        "theta",
        "--library",
        "poly3",
        "--out",
        tmp_path / "m.json",
    )
    assert code == 0, err
    assert "estimating velocities and accelerations" in out
    assert kept(tmp_path / "m.json") == TRUE_TERMS


def test_fit_quiet_prints_only_the_lagrangian(capsys, workdir, tmp_path):
    code, out, err = run(
        capsys,
        "fit",
        workdir / "data.csv",
        "--coordinates",
        "x,theta",
        "--angles",
        "theta",
        "--library",
        "poly3",
        "--quiet",
        "--out",
        tmp_path / "m.json",
    )
    assert code == 0 and err == ""
    assert out.count("\n") == 1 and out.startswith("L = ")


def test_fit_prints_r2_on_held_out_trajectories(capsys, tmp_path):
    """The R^2 printed as held-out is a refit's on a trajectory it did not see."""
    from lagsindy.library import CandidateLibrary

    data = pendulum_csv(tmp_path / "p.csv")
    code, out, err = run(
        capsys, "fit", tmp_path / "p.csv", *PENDULUM, "--out", tmp_path / "m.json"
    )
    assert code == 0, err
    found = re.search(
        r"R\^2 of forces over the test windows \(what the weak form fits\) on "
        r"held-out data ([-\d.]+) \(the last 1 of 4 trajectories, "
        r"scored by a refit on the rest, [\d.]+ s\); on the fitted data ([-\d.]+)",
        out,
    )
    assert found, out
    held, fitted = map(float, found.groups())
    # the same refit by hand (the fit is weak, as auto chooses on these data):
    # fit on trajectories 0-2, score on trajectory 3
    rest = data.groups != 3
    lib = CandidateLibrary.polynomial(["theta"], angles=["theta"], degree=2)
    sub = LagrangianSINDy(lib, formulation="weak", random_state=0)
    sub.fit(data.X[rest], data.tau[rest], groups=data.groups[rest])
    import torch

    Xt = torch.tensor(data.X)
    by_hand = sub.fitted_.weak_r2(Xt[~rest], data.tau[~rest], data.groups[~rest])
    assert held == pytest.approx(by_hand, abs=1e-4)
    est = LagrangianSINDy.load(tmp_path / "m.json")
    # the fitted rows: without the 3 rows at each end of every trajectory (as
    # fit(t=) leaves them out; here 24 of 1200)
    from lagsindy.differentiation import edge_rows

    inner = ~edge_rows(pd.read_csv(tmp_path / "p.csv")["t"].to_numpy(), data.groups)
    assert "24 of 1200 rows lie within 3 samples of a segment's end" in out
    assert fitted == pytest.approx(
        est.fitted_.weak_r2(Xt[inner], data.tau[inner], data.groups[inner]), abs=1e-4
    )
    assert held < fitted  # measured 0.9985 and 0.9992
    # one trajectory: its final time block is held out
    one = tmp_path / "one.csv"
    pd.read_csv(tmp_path / "p.csv").query("trajectory == 0").to_csv(one, index=False)
    code, out, err = run(capsys, "fit", one, *PENDULUM, "--out", tmp_path / "1.json")
    assert code == 0, err
    # (300 rows less the 6 edge rows)
    assert re.search(r"on held-out data [-\d.]+ \(the final 59 of 294 samples", out)
    # --held-out 0: no second fit, the score is labelled as on the fitted data
    code, out, err = run(
        capsys, "fit", one, *PENDULUM, "--held-out", "0", "--out", tmp_path / "0.json"
    )
    assert code == 0, err
    assert "held-out data" not in out and "second fit" not in out
    assert re.search(
        r"weak form fits\) on the fitted data [-\d.]+ \(--held-out 0\)", out
    )


def test_strong_form_on_estimated_derivatives_warns(capsys, tmp_path):
    warning = (
        "lagsindy fit: warning: the strong form was fitted to velocities and "
        "accelerations estimated from the positions: noise on these derivatives "
        "biases the coefficients (typically toward zero); prefer --formulation weak "
        "or auto"
    )
    pendulum_csv(tmp_path / "q.csv", ["trajectory", "t", "theta", "tau_theta"])
    pendulum_csv(tmp_path / "x.csv")
    for data, form, warned in (
        ("q.csv", "strong", True),
        ("q.csv", "weak", False),
        ("x.csv", "strong", False),  # derivatives given, not estimated
    ):
        code, _, err = run(
            capsys,
            "fit",
            tmp_path / data,
            *PENDULUM,
            "--formulation",
            form,
            "--quiet",
            "--out",
            tmp_path / "m.json",
        )
        assert code == 0, err
        assert err.splitlines().count(warning) == warned, (data, form, err)
        assert ("strong form was fitted" in err) == warned, (data, form, err)


def test_passive_fit_with_a_fixed_term(capsys, tmp_path):
    data = tmp_path / "passive.csv"
    assert (
        run(
            capsys,
            "simulate",
            "--system",
            "single_pendulum",
            "--passive",
            "--trajectories",
            "5",
            "--out",
            data,
        )[0]
        == 0
    )
    code, out, err = run(
        capsys,
        "fit",
        data,
        "--coordinates",
        "theta",
        "--angles",
        "theta",
        "--fixed-term",
        "theta_dot**2",
        "--out",
        tmp_path / "m.json",
    )
    assert code == 0, err
    est = LagrangianSINDy.load(tmp_path / "m.json")
    assert est.case_ == "fixed" and kept(tmp_path / "m.json") == {
        "theta_dot**2",
        "cos(theta)",
    }
    assert est.coef_[list(est.term_names_).index("cos(theta)")] == pytest.approx(
        19.62, rel=1e-3
    )


def test_missing_damping_warning_speaks_in_commands(tmp_path, capsys):
    """The fit's warning about a missing force names the command to run, not the
    Python call (before: 'lagsindy.diagnose', 'dissipation=DissipationLibrary')."""
    from lagsindy.systems import make_dataset, single_pendulum

    system = single_pendulum().with_damping(viscous={"theta": 0.2})
    data = make_dataset(
        system, n_trajectories=9, duration=3.0, excitation="sincos", random_state=0
    )
    csv = tmp_path / "damped.csv"
    data.to_frame().to_csv(csv, index=False)
    code, _, err = run(
        capsys, "fit", csv, "--coordinates", "theta", "--angles", "theta",
        "--raw-angles", "--out", tmp_path / "m.json", "--conservative",
    )  # fmt: skip
    assert code == 0
    (line,) = [x for x in err.splitlines() if "friction or damping missing" in x]
    assert "viscous(theta) = 0.2" in line
    assert "Run `lagsindy diagnose` on the same data" in line
    assert "lagsindy.diagnose" not in line and "dissipation=" not in line


def test_semicolon_csv_is_read_with_a_note(capsys, workdir, tmp_path):
    df = pd.read_csv(workdir / "data.csv")
    csv = tmp_path / "semi.csv"
    df.to_csv(csv, index=False, sep=";")
    code, out, err = run(
        capsys,
        "fit",
        csv,
        "--coordinates",
        "x,theta",
        "--angles",
        "theta",
        "--out",
        tmp_path / "m.json",
        "--quiet",
    )
    assert code == 0, err
    assert "semicolon-separated" in err
    assert "theta_dot*x_dot*cos(theta)" in out
    # decimal commas get a hint instead of a bare "not numeric"
    df.to_csv(csv, index=False, sep=";", decimal=",")
    code, _, err = run(
        capsys,
        "fit",
        csv,
        "--coordinates",
        "x,theta",
        "--angles",
        "theta",
        "--out",
        tmp_path / "m2.json",
    )
    assert code == 2 and "decimal commas" in err, err


def test_poly2_warns_that_it_cannot_couple_the_cart_and_pendulum(capsys, workdir):
    args = ["fit", workdir / "data.csv", "--coordinates", "x,theta"]
    args += ["--angles", "theta"]
    code, out, err = run(
        capsys, *args, "--library", "poly2", "--out", workdir / "p2.json", "--quiet"
    )
    assert code == 0
    assert "no term coupling the velocities of x and theta" in err, err
    assert "x_dot*theta_dot*cos(theta)" in err
    # the default library holds the coupling: the true structure, no warning
    code, out, err = run(capsys, *args, "--out", workdir / "p3.json", "--quiet")
    assert code == 0 and "coupling" not in err, err
    assert kept(workdir / "p3.json") == set(TRUE_TERMS)


def test_two_angles_need_a_product_of_both(capsys):
    from lagsindy.cli import _warn_missing_coupling
    from lagsindy.library import CandidateLibrary

    class Args:
        library = "poly3"

    coords = ["theta1", "theta2"]
    with pytest.warns(UserWarning, match="cos\\(theta1 - theta2\\).*poly4"):
        _warn_missing_coupling(
            CandidateLibrary.polynomial(coords, angles=coords, degree=3),
            coords,
            coords,
            Args,
        )
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lib = CandidateLibrary.polynomial(
            coords,
            angles=coords,
            degree=2,
            terms=["theta1_dot*theta2_dot*cos(theta1 - theta2)"],
        )
        _warn_missing_coupling(lib, coords, coords, Args)


def test_fit_chooses_the_window_and_says_which(capsys, tmp_path):
    """Positions only (noise 1e-2): the P-spline derivatives' smooth errors bias the
    81-sample window (6.1 % change to 161, 0.3 % from 161 to 321), so the default
    ("auto") keeps 161 and the summary says so; --window fixes it."""
    q = tmp_path / "q.csv"
    args = ["--trajectories", "20", "--duration", "5", "--noise", "0.01"]
    assert (
        run(
            capsys,
            "simulate",
            "--system",
            "cart_pendulum",
            *args,
            "--positions-only",
            "--seed",
            "0",
            "--out",
            q,
            "--quiet",
        )[0]
        == 0
    )
    fit = ["fit", q, "--coordinates", "x,theta", "--angles", "theta", "--held-out", "0"]
    code, out, err = run(capsys, *fit, "--out", tmp_path / "a.json")
    assert code == 0, err
    assert "(weak form, test window 161 samples)" in out + err
    assert "warning" not in err
    code, out, err = run(capsys, *fit, "--window", "81", "--out", tmp_path / "b.json")
    assert code == 0, err
    assert "(weak form, test window 81 samples)" in out + err
    assert LagrangianSINDy.load(tmp_path / "b.json").formulation.window == 81
    code, _, err = run(capsys, *fit, "--window", "3", "--out", tmp_path / "c.json")
    assert code == 2 and "--window must be at least 5" in err
    # the README's "auto" is accepted, as the default it is
    code, out, err = run(capsys, *fit, "--window", "auto", "--out", tmp_path / "d.json")
    assert code == 0 and "(weak form, test window 161 samples)" in out + err
    code, _, err = run(capsys, *fit, "--window", "wide", "--out", tmp_path / "e.json")
    assert code == 2 and "a whole number of samples or 'auto'" in err


def test_fit_refine_saves_the_refined_model(capsys, workdir, tmp_path):
    code, out, err = run(
        capsys, "fit", workdir / "data.csv", "--coordinates", "x,theta",
        "--angles", "theta", "--library", "poly3", "--refine", "50",
        "--held-out", "0", "--out", tmp_path / "r.json",
    )  # fmt: skip
    assert code == 0, err
    found = re.search(
        r"rollout refinement over (\d+) windows of 50 samples: RMSE ([\d.e-]+) -> "
        r"([\d.e-]+)", out
    )  # fmt: skip
    assert found, out
    assert int(found.group(1)) == 6 * 14  # 400 samples: starts 0, 25, ..., 325
    assert float(found.group(3)) <= float(found.group(2))
    sparse = LagrangianSINDy.load(workdir / "model.json")
    refined = LagrangianSINDy.load(tmp_path / "r.json")
    assert kept(tmp_path / "r.json") == kept(workdir / "model.json")
    assert not np.array_equal(refined.coef_, sparse.coef_)
    code, out, err = run(
        capsys, "fit", workdir / "data.csv", "--coordinates", "x,theta",
        "--refine", "1", "--out", tmp_path / "bad.json",
    )  # fmt: skip
    assert code != 0 and "--refine" in err


@pytest.mark.parametrize("copy", ["data.csv", "q.csv"])
def test_fit_refuses_rows_out_of_time_order(capsys, workdir, tmp_path, copy):
    """Rows whose 't' goes back were refused only when derivatives were estimated;
    with the derivative columns given they reached the weak form silently."""
    df = pd.read_csv(workdir / copy)
    rows = df.index.to_numpy().copy()
    rows[[50, 51]] = rows[[51, 50]]
    df.iloc[rows].to_csv(tmp_path / "swapped.csv", index=False)
    code, _, err = run(
        capsys, "fit", tmp_path / "swapped.csv", "--coordinates", "x,theta",
        "--angles", "theta", "--out", tmp_path / "m.json",
    )  # fmt: skip
    assert code == 2 and "'t' must increase within each trajectory" in err


_SPY = """
import sys

class Spy:  # says when torch starts to load
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            print("<<torch>>", flush=True)
            sys.meta_path.remove(self)
        return None

sys.meta_path.insert(0, Spy())
from lagsindy.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_fit_says_what_it_does_before_each_slow_step(workdir, tmp_path):
    """A line before torch loads, then one before each step that can take seconds
    (#44: a user waited 33 s in silence)."""
    proc = subprocess.run(
        [sys.executable, "-c", _SPY, "fit", str(workdir / "q.csv")]
        + ["--coordinates", "x,theta", "--angles", "theta", "--held-out", "0"]
        + ["--out", str(tmp_path / "m.json")],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    order = [
        rf"reading {re.escape(str(workdir / 'q.csv'))} and loading the fitting code",
        r"<<torch>>",
        r"building the candidate library poly3 over \['x', 'theta'\] \.\.\.",
        r"library poly3: \d+ terms \(\d+ of \d+ candidates removed as trivial or "
        r"dependent\), [\d.]+ s",
        r"estimating velocities and accelerations of \['x', 'theta'\]",
        r"36 of 2400 rows lie within 3 samples of a segment's end",
        r"fitting 2364 samples \(6 trajectories\) of \['x', 'theta'\]: forces from "
        r"\['tau_x', 'tau_theta'\], library poly3 \(\d+ terms\) \.\.\.",
        r"\[lagsindy\] stage 1",
        r"L = ",
    ]
    where = []
    for pattern in order:
        found = [i for i, line in enumerate(lines) if re.match(pattern, line)]
        assert found, (pattern, proc.stdout)
        where.append(found[0])
    assert where == sorted(where), proc.stdout
    assert where[0] == 0  # the first line comes before any heavy import
