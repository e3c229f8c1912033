"""Undriven coordinates and the chain library on the command line (issue #41):
``--input force,-``, ``--undriven theta``, ``--library chain``, ``--conservative``
and ``--delay auto`` that is not significant."""

import pytest

from tests._undriven import light_pendulum_data

from ._helpers import TRUE_TERMS, kept, run

CHAIN = ["--coordinates", "x,theta", "--angles", "theta", "--library", "chain"]


@pytest.fixture(scope="module")
def light_csv(tmp_path_factory):
    """A 0.1 kg pole under a damped 2 kg cart; one input column, ``force``."""
    _, data, _ = light_pendulum_data(0.05, 3.0)
    frame = data.to_frame()
    frame["force"] = data.tau[:, 0]
    frame = frame.drop(columns=[c for c in frame.columns if c.startswith("tau_")])
    path = tmp_path_factory.mktemp("undriven") / "light.csv"
    frame.to_csv(path, index=False)
    return path


@pytest.mark.parametrize(
    "marking",
    [["--input", "force,-"], ["--undriven", "theta", "--input", "force"]],
    ids=["input-dash", "undriven"],
)
def test_an_undriven_pole_fits_with_the_chain_library(
    capsys, light_csv, tmp_path, marking
):
    code, out, err = run(
        capsys, "fit", light_csv, *CHAIN, *marking, "--out", tmp_path / "m.json"
    )
    assert code == 0, err
    assert kept(tmp_path / "m.json") == TRUE_TERMS | {"viscous(x)"}
    assert "forces from ['force', '-']" in out
    assert "library chain (8 terms)" in out
    # the joint fit, said in command-line words
    (line,) = [x for x in err.splitlines() if "fitted jointly" in x]
    assert "pass --conservative" in line and "DissipationLibrary([])" not in line
    # measured: held-out R^2 0.9999 (a refit with the same dissipation)
    assert "on held-out data 0.99" in out


def test_conservative_keeps_the_conservative_fit(capsys, light_csv, tmp_path):
    code, _, err = run(
        capsys, "fit", light_csv, *CHAIN, "--input", "force,-", "--conservative",
        "--out", tmp_path / "m.json", "--quiet",
    )  # fmt: skip
    assert code == 0, err
    assert "fitted jointly" not in err
    assert "friction or damping missing from the model" in err


@pytest.mark.parametrize(
    "options, message",
    [
        (["--undriven", "phi", "--input", "force"], "--undriven names 'phi'"),
        (["--input", "force"], "'-' for an undriven one"),
        (["--input=-,-"], "every coordinate is marked undriven"),
        (["--input", "0,0"], "every coordinate is marked undriven"),
        (["--undriven", "theta", "--input", "force,force"], "write '-' for theta"),
        (["--undriven", "theta"], "not in the data; name them with --input"),
        (["--undriven", "theta", "--passive"], "drop one of them"),
    ],
)
def test_undriven_mistakes_end_with_one_line(
    capsys, light_csv, tmp_path, options, message
):
    code, _, err = run(
        capsys, "fit", light_csv, *CHAIN, *options, "--out", tmp_path / "m.json"
    )
    assert code == 2
    assert message in err and "Traceback" not in err


def test_an_unknown_library_names_chain(capsys, light_csv, tmp_path):
    code, _, err = run(
        capsys, "fit", light_csv, "--coordinates", "x,theta", "--library", "chian",
        "--input", "force,-", "--out", tmp_path / "m.json",
    )  # fmt: skip
    assert code == 2 and "chain (a chain of links" in err


def test_predict_reads_an_undriven_input(capsys, light_csv, tmp_path):
    import pandas as pd

    model = tmp_path / "m.json"
    assert (
        run(capsys, "fit", light_csv, *CHAIN, "--input", "force,-", "--out", model,
            "--quiet")[0] == 0
    )  # fmt: skip
    code, _, err = run(
        capsys, "predict", model, light_csv, "--undriven", "theta", "--input",
        "force", "--out", tmp_path / "p.csv", "--quiet",
    )  # fmt: skip
    assert code == 0, err
    assert "theta_ddot" in pd.read_csv(tmp_path / "p.csv").columns
