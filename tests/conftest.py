import os

import numpy as np
import pytest
import torch
from _helpers import first_problem  # noqa: F401  (used by fixtures)

from lagsindy import LagrangianSINDy
from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum


def pytest_configure(config):
    """Under pytest-xdist the workers are the parallelism: one thread each.

    With ``-n 2`` on two cores, two workers that each start two torch (and BLAS)
    threads share the cores four ways; a measured diagnosis test ran 5x slower
    in the suite than alone. Subprocesses started by tests inherit the setting.
    """
    if os.environ.get("PYTEST_XDIST_WORKER"):
        for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            os.environ.setdefault(name, "1")
        torch.set_num_threads(1)


@pytest.fixture
def fit_rows(monkeypatch):
    """Rows of every ``LagrangianSINDy.fit`` made from here on, in order (clear the
    list to count from a later point)."""
    rows = []
    original = LagrangianSINDy.fit

    def recorded(self, X, *args, **kwargs):
        rows.append(len(X))
        return original(self, X, *args, **kwargs)

    monkeypatch.setattr(LagrangianSINDy, "fit", recorded)
    return rows


@pytest.fixture
def reused_grams(monkeypatch):
    """One entry per weak-form statistics served from kept ones from here on
    (``weak_integrals._reused_grams``, see ``reuse_weak_columns``)."""
    from lagsindy.formulation import weak_integrals

    calls = []
    original = weak_integrals._reused_grams

    def spy(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(weak_integrals, "_reused_grams", spy)
    return calls


@pytest.fixture(autouse=True)
def _seed():
    """Tests that draw random numbers themselves start from a known state."""
    np.random.seed(0)
    torch.manual_seed(0)
    yield


@pytest.fixture(scope="session")
def cart_active():
    """Paper-size noise-free cart-pendulum data, tau = a sin(wt) + b cos(wt) on the cart."""
    return make_dataset(cart_pendulum(), excitation="sincos", random_state=0)


@pytest.fixture(scope="session")
def single_active():
    return make_dataset(
        single_pendulum(), n_trajectories=40, excitation="paper", random_state=1
    )


@pytest.fixture(scope="session")
def single_passive():
    return make_dataset(
        single_pendulum(), n_trajectories=40, excitation=None, random_state=2
    )


@pytest.fixture(scope="session")
def pend():
    """A short forced single pendulum (the paper's input): 4 noise-free
    trajectories of 2 s, 800 rows (the bad-input tests' messages name that count)."""
    return make_dataset(
        single_pendulum(), n_trajectories=4, duration=2.0, random_state=0
    )


@pytest.fixture(scope="session")
def cart():
    """A short forced cart-pendulum: 2 noise-free trajectories of 1 s."""
    return make_dataset(
        cart_pendulum(),
        n_trajectories=2,
        duration=1.0,
        excitation="sincos",
        random_state=0,
    )


@pytest.fixture(scope="session")
def pendulum():
    """A forced single pendulum (the paper's input), 10 noise-free trajectories."""
    return make_dataset(
        single_pendulum(), n_trajectories=10, excitation="paper", random_state=1
    )


@pytest.fixture(scope="session")
def noisy_pendulum():
    """A forced single pendulum, 8 trajectories of 2 s, position noise 0.01 with
    P-spline derivatives (the "sensor" protocol)."""
    return make_dataset(
        single_pendulum(),
        n_trajectories=8,
        duration=2.0,
        excitation="paper",
        noise=0.01,
        protocol="sensor",
        random_state=0,
    )


@pytest.fixture(scope="session")
def case_iii_problem():
    """The case III Problem of a noisy passive cart-pendulum search."""
    system = cart_pendulum()
    data = make_dataset(
        system,
        n_trajectories=4,
        excitation=None,
        protocol="paper",
        noise=0.05,
        random_state=0,
    )
    return first_problem(
        LagrangianSINDy(system.paper_library(), random_state=0), data.X
    )


