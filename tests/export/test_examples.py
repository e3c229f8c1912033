"""The control examples run (quick mode) and balance the true cart-pendulum.

examples/control_lqr_cartpole.py: LQR on the linearization of a model identified
from noisy data; examples/control_mpc_cartpole.py: MPC with CasADi (it says it is
skipped when CasADi is not installed). Both run at once as subprocesses.
"""

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
# the control examples at quick size still take ~30 s of CPU (the gallery runs them too)
pytestmark = pytest.mark.slow
SCRIPTS = ("control_lqr_cartpole.py", "control_mpc_cartpole.py")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "LAGSINDY_EXAMPLE_QUICK": "1",
        "OMP_NUM_THREADS": "1",
    }
    procs = {
        name: subprocess.Popen(
            [sys.executable, str(ROOT / "examples" / name)],
            cwd=tmp_path_factory.mktemp(name[:-3]),
            env=env,
            text=True,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        for name in SCRIPTS
    }
    results = {}
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=600)
        results[name] = (out, err, proc.returncode)
    return results


def _check(result):
    out, err, code = result
    assert code == 0, err[-2000:]
    assert "Traceback" not in err
    return out


def test_lqr_balances_the_true_cart_pendulum(runs):
    out = _check(runs["control_lqr_cartpole.py"])
    assert "learned: L = " in out
    assert "stabilized: True" in out, out[-2000:]


def test_mpc_balances_it_or_says_casadi_is_missing(runs):
    out = _check(runs["control_mpc_cartpole.py"])
    if importlib.util.find_spec("casadi") is None:
        assert "MPC example skipped" in out
    else:
        assert "stabilized: True" in out, out[-2000:]
