"""``lagsindy diagnose``."""

import json
import subprocess
import sys

import pytest

from lagsindy.cli import main

from ._helpers import ENV


def test_diagnose_command_finds_damping(tmp_path, capsys):
    from lagsindy.systems import make_dataset, single_pendulum

    system = single_pendulum().with_damping(viscous={"theta": 0.2})
    data = make_dataset(
        system, n_trajectories=9, duration=3.0, excitation="sincos", random_state=0
    )
    csv = tmp_path / "damped.csv"
    data.to_frame().to_csv(csv, index=False)
    plot = tmp_path / "diag.png"
    final = tmp_path / "final.json"
    rc = main(
        [
            "diagnose",
            str(csv),
            "--coordinates",
            "theta",
            "--angles",
            "theta",
            "--raw-angles",
            "--plot",
            str(plot),
            "--out-model",
            str(final),
            "--quiet",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0
    assert "viscous(theta)" in out and "viscous damping" in out and "D = " in out
    assert plot.stat().st_size > 1000
    from lagsindy import LagrangianSINDy

    loaded = LagrangianSINDy.load(final)
    kept = {
        t.name: c
        for t, c in zip(loaded.dissipation_terms_, loaded.dissipation_coef_)
        if c != 0
    }  # (the joint fit's library also holds coulomb(theta), pruned)
    assert kept == {"viscous(theta)": pytest.approx(0.2, rel=1e-3)}
    # and from the saved model of the first fit, with a bad pairing: one-line error
    first = tmp_path / "first.json"
    assert (
        main(
            [
                "fit",
                str(csv),
                "--coordinates",
                "theta",
                "--angles",
                "theta",
                "--out",
                str(first),
                "--conservative",
                "--quiet",
            ]
        )
        == 0
    )
    # (a conservative fit: the default refits jointly with damping)
    # the undamped model's coefficients move with the window (0.2 damping is
    # missing), and the probes name the damping; both point at the command
    err = capsys.readouterr().err
    assert "run `lagsindy diagnose`" in err and "lagsindy.diagnose" not in err
    assert "viscous(theta) = 0.2" in err
    assert main(["diagnose", str(csv), "--model", str(first), "--passive"]) == 2
    err = capsys.readouterr().err
    assert "error:" in err and len(err.strip().splitlines()) == 1


def test_quiet_fit_then_quiet_diagnose_print_only_results(tmp_path, capsys):
    from lagsindy.systems import make_dataset, single_pendulum

    system = single_pendulum().with_damping(viscous={"theta": 0.2})
    data = make_dataset(
        system, n_trajectories=9, duration=3.0, excitation="sincos", random_state=0
    )
    csv = tmp_path / "damped.csv"
    data.to_frame().to_csv(csv, index=False)
    model = tmp_path / "m.json"

    def cli(*args):
        return subprocess.run(
            [sys.executable, "-m", "lagsindy", *map(str, args)],
            cwd=tmp_path,
            env=ENV,
            capture_output=True,
            text=True,
            timeout=300,
        )

    # not quiet: the fit prints its stage lines (in-process: one interpreter start
    # less; the quiet diagnose below runs in its own process, whose stderr must be
    # empty) ...
    args = ["fit", csv, "--coordinates", "theta", "--angles", "theta"]
    assert main([*map(str, args), "--out", str(model), "--held-out", "0"]) == 0
    assert "[lagsindy] stage" in capsys.readouterr().out
    # ... but the saved model does not carry that verbosity
    assert "verbose" not in json.loads(model.read_text())["hyperparameters"]
    diag = cli("diagnose", csv, "--model", model, "--quiet")
    assert diag.returncode == 0, diag.stderr
    assert "[lagsindy]" not in diag.stdout and "stage" not in diag.stdout
    assert diag.stdout.startswith("Residual diagnosis"), diag.stdout[:300]
    assert diag.stderr == ""
    # without --quiet, diagnose still prints no per-fold stage lines (in-process)
    assert main(["diagnose", str(csv), "--model", str(model)]) == 0
    assert "[lagsindy] stage" not in capsys.readouterr().out
