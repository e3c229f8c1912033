"""Helpers shared by the command-line tests (fixtures are in ``conftest.py``)."""

import os
from pathlib import Path

from lagsindy import LagrangianSINDy
from lagsindy.cli import main

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
TRUE_TERMS = {"x_dot**2", "theta_dot**2", "theta_dot*x_dot*cos(theta)", "cos(theta)"}
PENDULUM = ["--coordinates", "theta", "--angles", "theta", "--library", "poly2"]


def run(capsys, *args):
    """``lagsindy ARGS`` in this process: (exit status, stdout, stderr)."""
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def kept(path):
    """The terms a saved model keeps."""
    table = LagrangianSINDy.load(path).coef_table()
    return set(table.term[table.kept])


def pendulum_csv(path, columns=None):
    """A small forced pendulum data set (4 trajectories x 3 s, sigma 0.01) as CSV."""
    from lagsindy.systems import make_dataset, single_pendulum

    data = make_dataset(
        single_pendulum(),
        n_trajectories=4,
        duration=3.0,
        excitation="sincos",
        noise=0.01,
        random_state=0,
    )
    frame = data.to_frame()
    (frame if columns is None else frame[columns]).to_csv(path, index=False)
    return data
